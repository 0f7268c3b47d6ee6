"""GEN-LAL's regressor f: a 1-D CNN over the predicted mesh, joined with the actuator features, → error reduction.

The paper's network: batch normalization first (on the x, y, z channels), then convolutions of depth
3 → 9 → 18 → 27 → 18 → 9 → 3 → 1 with kernels 32, 16, 16, 8, 8, 4, 4, 4 and stride 2, trained with dropout 0.5.
The paper lists eight kernels for seven channel changes; here the eighth kernel is a last 1 → 1 convolution, so
every listed kernel is used. Convolutions are padded (``k // 2``) so any vertex count works, and the result is
average-pooled to a fixed length of 4 before it is joined with the actuator values and the labelled-set scalars
(``offline.active.features``) in a small dense head (32 units, dropout 0.5), because the paper does not say how
the two are joined and the pooled length must not depend on the mesh (a policy should carry over to a refined
mesh). Trained with Adam on mean-squared error, seeded.
"""

from __future__ import annotations

import io
from collections.abc import Callable

import numpy as np

from offline.active.features import CandidateFeatures

CHANNELS = (3, 9, 18, 27, 18, 9, 3, 1, 1)
KERNELS = (32, 16, 16, 8, 8, 4, 4, 4)
POOLED = 4


def build_cnn(n_act: int, n_extra: int, dropout: float = 0.5):
    """The regressor module: ``forward(mesh (B, 3, V), side (B, A + E)) -> (B,)``."""
    import torch
    from torch import nn

    class DeltaCnn(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            layers: list[nn.Module] = [nn.BatchNorm1d(3)]
            for i, k in enumerate(KERNELS):
                layers.append(nn.Conv1d(CHANNELS[i], CHANNELS[i + 1], k, stride=2, padding=k // 2))
                layers.append(nn.ReLU())
            layers.append(nn.AdaptiveAvgPool1d(POOLED))
            self.conv = nn.Sequential(*layers)
            self.head = nn.Sequential(nn.Linear(POOLED + n_act + n_extra, 32), nn.ReLU(), nn.Dropout(dropout),
                                      nn.Linear(32, 1))

        def forward(self, mesh: torch.Tensor, side: torch.Tensor) -> torch.Tensor:
            z = self.conv(mesh).flatten(1)
            return self.head(torch.cat([z, side], dim=1)).squeeze(1)

    return DeltaCnn()


def _side(f: CandidateFeatures) -> np.ndarray:
    return np.concatenate([f.act, f.extra], axis=1).astype(np.float32)


def train_regressor(features: CandidateFeatures, target: np.ndarray, epochs: int = 60, batch: int = 64,
                    lr: float = 1e-3, seed: int = 0, log: Callable[[str], None] | None = None) -> bytes:
    """Fit the CNN to ``target`` (n,) (standardized reductions); returns the serialized module state."""
    import torch

    torch.manual_seed(seed)
    model = build_cnn(features.act.shape[1], features.extra.shape[1])
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=1e-4)
    mesh = torch.from_numpy(features.mesh)
    side = torch.from_numpy(_side(features))
    y = torch.from_numpy(np.asarray(target, np.float32))
    rng = np.random.default_rng(seed)
    n = len(y)
    for epoch in range(epochs):
        model.train()
        perm = rng.permutation(n)
        total = 0.0
        for s in range(0, n, batch):
            idx = torch.from_numpy(perm[s:s + batch])
            if len(idx) < 2:
                continue  # batch normalization needs two samples
            loss = torch.mean((model(mesh[idx], side[idx]) - y[idx]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.item() * len(idx)
        if log and (epoch % 20 == 0 or epoch == epochs - 1):
            log(f"policy regressor epoch {epoch}: train MSE {total / n:.4f}")
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    return buf.getvalue()


def predict_reduction(state: bytes, features: CandidateFeatures) -> np.ndarray:
    """Predicted (standardized) error reduction of every candidate, with the regressor in evaluation mode."""
    import torch

    model = build_cnn(features.act.shape[1], features.extra.shape[1])
    model.load_state_dict(torch.load(io.BytesIO(state), weights_only=True))
    model.eval()
    out = []
    with torch.no_grad():
        for s in range(0, len(features.act), 256):
            out.append(model(torch.from_numpy(features.mesh[s:s + 256]),
                             torch.from_numpy(_side(features)[s:s + 256])).numpy())
    return np.concatenate(out) if out else np.zeros(0)
