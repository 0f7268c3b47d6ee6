"""KSNN training in PyTorch (offline only): three shallow networks (x, y, z) from actuators to vertex offsets.

As in the paper: inputs normalized to [0, 1], one tanh hidden layer, a linear output layer per axis, Adam with
mean-squared error, and the best checkpoint (lowest validation loss) kept. The caller passes the dataset's train
and validation poses (``offline.dataset.splits``); the test poses never reach this module. Targets are scaled per
axis to unit standard deviation for training; the scale is folded back into the exported weights. Checkpoints
are written atomically every few epochs, so a killed training resumes.
"""

from __future__ import annotations

import hashlib
import io
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.predictor import KsnnWeights


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults fit the coarse sample mesh on a laptop CPU)."""

    epochs: int = 300
    batch_size: int = 64
    lr: float = 3e-3
    weight_decay: float = 0.0
    seed: int = 0
    patience: int = 60  # epochs without validation improvement before stopping early
    threads: int = 1
    checkpoint_every_s: float = 5.0
    #: Pin the prediction at the dataset's rest pose to exactly zero (when the dataset records one): the network
    #: is trained as f(x) - f(x_rest), which is again a KSNN (the output bias becomes -f(x_rest) without it).
    rest_anchor: bool = True
    #: Weight of the surface-strain term beside the offsets' scaled MSE: the mean squared error of every surface
    #: edge's vector divided by its rest length (a strain, dimensionless). 0 trains on offsets alone.
    edge_weight: float = 0.0
    #: The power p of the offsets' term: the mean of each vertex's squared scaled error (over the axes) to the p/2,
    #: to the 2/p: 2 is the MSE; a larger p weighs a pose's worst vertices more, so the fit aims at the max error
    #: (a least-squares fit leaves its largest errors on a few rim vertices, where a max-aimed one need not).
    error_power: float = 2.0
    #: The rank r of each axis' output layer (0: full, r = H): W2 = C U with C (H × r), U (r × V), so H tanh units
    #: feed r output directions. A wide hidden layer of lower output rank fits poses better than a square one of the
    #: same in-cycle solve cost (its Gauss-Newton step costs O(r H A), :mod:`models.ksnn_solve`).
    #: An integer or a multiple of the actuator count such as ``"2A"``.
    output_rank: int | str = 0
    #: A hinge on the tail of the error, in metres (0: none): beside the offsets' term, ``tail_weight`` × the mean
    #: over poses and vertices of max(0, |e| − ``tail_threshold``)², |e| a vertex's Euclidean error, in the scaled
    #: units of the MSE. Only errors past the threshold pay it, so the fit is pulled at its largest errors without
    #: the whole surface reweighted (as a larger ``error_power`` does, at the mean's cost).
    tail_threshold: float = 0.0
    tail_weight: float = 0.0
    #: Start from the best weights of an earlier run's checkpoint (``OUT/checkpoints/ksnn_h<H>.pt``) instead of a
    #: random draw: a fine-tune with other settings (a smaller learning rate, a hinge on the tail) on the same
    #: dataset and split; "" starts afresh.
    init: str = ""


@dataclass
class TrainResult:
    """The best weights found for one hidden size, with the loss history (per epoch, scaled units)."""

    hidden: int
    weights: KsnnWeights
    best_epoch: int
    best_val_mse: float
    history: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0


def hidden_candidates(n_actuators: int) -> list[int]:
    """Hidden sizes tried by validation: A, 1.5 A and 2 A."""
    return sorted({n_actuators, math.ceil(1.5 * n_actuators), 2 * n_actuators})


def resolve_hidden(spec: Sequence[int | str] | None, n_actuators: int) -> list[int]:
    """Hidden sizes from a user list: integers, or multiples of the actuator count written ``A``, ``1.5A``, ``2A``.

    ``["A"]`` is the paper's H = A option alone; None gives :func:`hidden_candidates`.
    """
    if not spec:
        return hidden_candidates(n_actuators)
    out: set[int] = set()
    for item in spec:
        text = str(item).strip()
        try:
            if text.upper().endswith("A"):
                factor = float(text[:-1]) if text[:-1] else 1.0
                value = math.ceil(factor * n_actuators)
            else:
                value = int(text)
        except ValueError:
            raise ValueError(f"hidden size {item!r}: expected an integer or a multiple of A such as A, 1.5A, 2A"
                             ) from None
        if value < 1:
            raise ValueError(f"hidden size {item!r} gives {value}; must be at least 1")
        out.add(value)
    return sorted(out)


def output_rank(spec: int | str, n_actuators: int) -> int:
    """The output layer's rank from :attr:`TrainConfig.output_rank`: 0 (full), an integer, or a multiple of A."""
    if spec in (0, "0", "", None):
        return 0
    try:
        return resolve_hidden([spec], n_actuators)[0]
    except ValueError:
        raise ValueError(f"output rank {spec!r}: expected 0 (full), an integer or a multiple of A such as 2A"
                         ) from None


def _module(n_in: int, hidden: int, n_out: int, anchor: np.ndarray | None = None, rank: int = 0):
    """The KSNN module; with ``anchor`` (a normalized pose) its output is f(x) - f(anchor), zero at the anchor.
    With ``rank`` r (0 < r < hidden) each axis' output layer is the product C U (H × r, r × V)."""
    import torch

    class Ksnn(torch.nn.Module):
        """Three independent one-hidden-layer tanh networks, stored as batched weights (axis-major)."""

        def __init__(self) -> None:
            super().__init__()
            self.W1 = torch.nn.Parameter(torch.empty(3, n_in, hidden))
            self.b1 = torch.nn.Parameter(torch.empty(3, 1, hidden))
            low = 0 < rank < hidden
            if low:
                self.C = torch.nn.Parameter(torch.empty(3, hidden, rank))
                self.U = torch.nn.Parameter(torch.empty(3, rank, n_out))
            else:
                self.W2 = torch.nn.Parameter(torch.empty(3, hidden, n_out))
            self.b2 = torch.nn.Parameter(torch.zeros(3, 1, n_out))
            bound1 = 1.0 / math.sqrt(n_in)
            torch.nn.init.uniform_(self.W1, -3 * bound1, 3 * bound1)
            torch.nn.init.uniform_(self.b1, -1.0, 1.0)
            if low:
                torch.nn.init.uniform_(self.C, -1.0 / math.sqrt(hidden), 1.0 / math.sqrt(hidden))
                torch.nn.init.uniform_(self.U, -1.0 / math.sqrt(rank), 1.0 / math.sqrt(rank))
            else:
                torch.nn.init.uniform_(self.W2, -1.0 / math.sqrt(hidden), 1.0 / math.sqrt(hidden))
            self.anchor = None if anchor is None else torch.from_numpy(
                np.asarray(anchor, dtype=np.float32).reshape(1, 1, n_in))

        def output(self, h: torch.Tensor) -> torch.Tensor:
            return torch.matmul(torch.matmul(h, self.C), self.U) if hasattr(self, "C") else torch.matmul(h, self.W2)

        def forward(self, x: torch.Tensor) -> torch.Tensor:  # x (B, A) in [0, 1] → (3, B, V)
            h = torch.tanh(torch.matmul(x.unsqueeze(0), self.W1) + self.b1)
            if self.anchor is not None:  # b2 drops out of f(x) - f(anchor)
                return self.output(h - torch.tanh(torch.matmul(self.anchor, self.W1) + self.b1))
            return self.output(h) + self.b2

    return Ksnn()


def offsets_term(diff: Any, power: float) -> Any:
    """The offsets' part of the loss on (3, B, V) scaled errors: the MSE at ``power`` 2, else the mean over vertices
    of (their squared error averaged over the axes) to the ``power``/2, to the 2/``power`` (the same units)."""
    import torch

    if power == 2.0:
        return torch.mean(diff ** 2)
    per_vertex = torch.mean(diff ** 2, dim=0)  # (B, V)
    return torch.mean(per_vertex ** (0.5 * power)) ** (2.0 / power)


def tail_term(diff: Any, scale: Any, threshold: float) -> Any:
    """The mean over poses and vertices of max(0, |e| − ``threshold``)² on (3, B, V) scaled errors, |e| a vertex's
    Euclidean error in metres (``scale`` (3, 1, 1): metres per scaled unit), divided by the mean squared scale: in
    the scaled units of the MSE."""
    import torch

    err = torch.sqrt(torch.sum((diff * scale) ** 2, dim=0) + 1e-30)  # (B, V) metres
    return torch.mean(torch.relu(err - threshold) ** 2) / torch.mean(scale ** 2)


def make_objective(scale: np.ndarray, edges: tuple[np.ndarray, np.ndarray] | None, edge_weight: float,
                   error_power: float = 2.0, tail_threshold: float = 0.0,
                   tail_weight: float = 0.0) -> Callable[[Any, Any], Any]:
    """The training loss on (3, B, V) tensors of per-axis scaled offsets: their MSE (or the power mean of
    :func:`offsets_term`), plus ``edge_weight`` × the mean squared edge strain error, (Δu_i − Δu_j) / |x_i − x_j|
    per surface edge and axis, in metres over metres, plus ``tail_weight`` × the :func:`tail_term` past
    ``tail_threshold`` metres."""
    if not error_power >= 2.0:
        raise ValueError(f"error_power must be at least 2, got {error_power}")
    if not (tail_threshold >= 0 and tail_weight >= 0):
        raise ValueError(f"tail_threshold and tail_weight must be zero or positive, got {tail_threshold}, "
                         f"{tail_weight}")
    power = float(error_power)
    import torch

    if tail_weight > 0:
        scale_t = torch.from_numpy(np.asarray(scale, np.float32)).view(3, 1, 1)
        inner = make_objective(scale, edges, edge_weight, error_power)
        threshold, weight = float(tail_threshold), float(tail_weight)
        return lambda pred, target: (inner(pred, target)
                                     + weight * tail_term(pred - target, scale_t, threshold))
    if edges is None or edge_weight <= 0:
        return lambda pred, target: offsets_term(pred - target, power)

    e_i = torch.from_numpy(np.asarray(edges[0][:, 0], np.int64))
    e_j = torch.from_numpy(np.asarray(edges[0][:, 1], np.int64))
    inv_len = (torch.from_numpy(np.asarray(scale, np.float32)).view(3, 1, 1)
               / torch.from_numpy(np.asarray(edges[1], np.float32)).view(1, 1, -1))  # scaled units → strain

    def objective(pred: Any, target: Any) -> Any:
        diff = pred - target
        strain = (diff[:, :, e_i] - diff[:, :, e_j]) * inv_len
        return offsets_term(diff, power) + edge_weight * torch.mean(strain ** 2)

    return objective


def train_ksnn(x_norm: np.ndarray, offsets: np.ndarray, train_idx: np.ndarray, val_idx: np.ndarray, hidden: int,
               lo: np.ndarray, hi: np.ndarray, config: TrainConfig, checkpoint: Path | None = None,
               log: Callable[[str], None] | None = None, anchor: np.ndarray | None = None,
               edges: tuple[np.ndarray, np.ndarray] | None = None) -> TrainResult:
    """Train one KSNN with ``hidden`` units; ``offsets`` (N, V, 3) may be a memmap (batches are read on demand).

    ``anchor``: a normalized pose whose offsets are zero by construction (the rest pose); the network is then
    trained and exported so that it predicts exactly zero there. ``edges``: the surface's edges (E, 2) and their
    rest lengths (E,), needed when ``config.edge_weight`` > 0. Resumes from ``checkpoint`` when it exists and
    matches the problem; returns the best weights in SI-scaled form. The validation objective (early stopping,
    the best epoch) is the training loss: scaled MSE plus ``edge_weight`` × edge-strain MSE.
    """
    import torch

    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed + hidden)
    n_act = x_norm.shape[1]
    n_vert = offsets.shape[1]
    # Per-axis output scaling from the training poses (read in chunks: offsets may not fit in memory).
    mean = np.zeros((3, n_vert))
    sq = np.zeros(3)
    for s in range(0, len(train_idx), 256):
        chunk = np.asarray(offsets[train_idx[s:s + 256]], dtype=np.float64)
        mean += chunk.sum(axis=0).T
        sq += (chunk ** 2).sum(axis=(0, 1))
    mean /= len(train_idx)
    var = sq / (len(train_idx) * n_vert) - (mean ** 2).mean(axis=1)
    scale = np.sqrt(np.maximum(var, 1e-30))
    rank = output_rank(config.output_rank, n_act)
    rank = rank if rank < hidden else 0
    model = _module(n_act, hidden, n_vert, anchor, rank)
    with torch.no_grad():
        model.b2.copy_(torch.from_numpy((mean / scale[:, None])[:, None, :]).float())
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=max(5, config.patience // 4))
    scale_t = torch.from_numpy(scale).float().view(3, 1, 1)
    lam = float(config.edge_weight)
    if lam > 0 and edges is None:
        raise ValueError("edge_weight > 0 needs the surface's edges and rest lengths")
    objective = make_objective(scale, edges, lam, config.error_power, config.tail_threshold, config.tail_weight)
    history: dict[str, list[float]] = {"train": [], "val": [], "lr": []}
    start_epoch = 0
    best = {"val": math.inf, "epoch": -1, "state": None}
    # The checkpoint belongs to these exact train / validation poses: a changed split starts afresh.
    split_id = hashlib.sha1(np.asarray(train_idx, np.int64).tobytes() + b"|" +
                            np.asarray(val_idx, np.int64).tobytes()).hexdigest()[:16]
    key = {"n_act": n_act, "n_vert": n_vert, "hidden": hidden, "n_train": len(train_idx), "seed": config.seed,
           "split": split_id, "anchor": None if anchor is None else [float(a) for a in anchor]}
    if lam > 0:  # (absent at 0, so checkpoints written before the edge term still resume)
        key["edge_weight"] = lam
    if config.error_power != 2.0:  # (absent at 2, so earlier checkpoints still resume)
        key["error_power"] = float(config.error_power)
    if rank:  # (absent at full rank, likewise)
        key["output_rank"] = rank
    if config.weight_decay > 0:  # (absent without decay, likewise)
        key["weight_decay"] = float(config.weight_decay)
    if config.tail_weight > 0:  # (absent without the tail's hinge, likewise)
        key["tail"] = [float(config.tail_threshold), float(config.tail_weight)]
    if config.init:
        key["init"] = _init_from(model, Path(config.init), scale)
    if checkpoint is not None and checkpoint.exists():
        ck = torch.load(checkpoint, weights_only=False)
        if ck.get("key") == key:
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["opt"])
            sched.load_state_dict(ck["sched"])
            history = ck["history"]
            best = ck["best"]
            start_epoch = ck["epoch"] + 1
            if log:
                log(f"H={hidden}: resumed at epoch {start_epoch} (best val {best['val']:.4g} at {best['epoch']})")

    def batch_targets(idx: np.ndarray) -> torch.Tensor:
        y = np.asarray(offsets[np.sort(idx)], dtype=np.float32)  # (B, V, 3); sorted reads suit a memmap
        order = np.argsort(np.argsort(idx))
        y = y[order]
        return torch.from_numpy(np.ascontiguousarray(y.transpose(2, 0, 1))) / scale_t

    def save(epoch: int) -> None:
        if checkpoint is None:
            return
        buf = io.BytesIO()
        torch.save({"key": key, "model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                    "history": history, "best": best, "epoch": epoch, "scale": scale}, buf)
        write_bytes(checkpoint, buf.getvalue())

    x_t = torch.from_numpy(x_norm.astype(np.float32))
    rng = np.random.default_rng(config.seed * 7919 + hidden)
    for _ in range(start_epoch):  # keep the shuffle stream identical after a resume
        rng.permutation(len(train_idx))
    t0 = time.perf_counter()
    last_save = time.monotonic()
    epoch = start_epoch - 1
    val_targets = batch_targets(val_idx) if len(val_idx) * n_vert * 3 <= 50_000_000 else None
    for epoch in range(start_epoch, config.epochs):
        model.train()
        perm = train_idx[rng.permutation(len(train_idx))]
        total = 0.0
        for s in range(0, len(perm), config.batch_size):
            idx = perm[s:s + config.batch_size]
            pred = model(x_t[idx])
            loss = objective(pred, batch_targets(idx))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        train_mse = total / len(perm)
        model.eval()
        with torch.no_grad():
            if val_targets is not None:
                val_mse = float(objective(model(x_t[val_idx]), val_targets))
            else:
                acc = 0.0
                for s in range(0, len(val_idx), 256):
                    idx = val_idx[s:s + 256]
                    acc += float(objective(model(x_t[idx]), batch_targets(idx))) * len(idx)
                val_mse = acc / len(val_idx)
        sched.step(val_mse)
        history["train"].append(train_mse)
        history["val"].append(val_mse)
        history["lr"].append(opt.param_groups[0]["lr"])
        if val_mse < best["val"]:
            best = {"val": val_mse, "epoch": epoch, "state": {k: v.clone() for k, v in model.state_dict().items()}}
        if log and (epoch % 25 == 0 or epoch == config.epochs - 1):
            log(f"H={hidden} epoch {epoch}: train {train_mse:.4g} val {val_mse:.4g} (best {best['val']:.4g})")
        if time.monotonic() - last_save > config.checkpoint_every_s:
            save(epoch)
            last_save = time.monotonic()
        if epoch - best["epoch"] >= config.patience:
            if log:
                log(f"H={hidden}: no improvement for {config.patience} epochs, stopping at epoch {epoch}")
            break
    save(epoch)
    state = best["state"] if best["state"] is not None else model.state_dict()
    return TrainResult(hidden=hidden, weights=_to_weights(state, scale, lo, hi, anchor), best_epoch=int(best["epoch"]),
                       best_val_mse=float(best["val"]), history=history, seconds=time.perf_counter() - t0)


def _init_from(model: Any, path: Path, scale: np.ndarray) -> str:
    """Load the best weights of the checkpoint at ``path`` into ``model``; returns the file's sha256 (16 hex). It
    must hold a network of the same form, trained on the same training poses (the same per-axis output scale)."""
    import torch

    if not path.is_file():
        raise ValueError(f"init checkpoint {path}: no such file")
    data = path.read_bytes()
    ck = torch.load(io.BytesIO(data), weights_only=False)
    state = (ck.get("best") or {}).get("state") if isinstance(ck, dict) else None
    if state is None:
        raise ValueError(f"init checkpoint {path}: holds no best weights (not a training checkpoint)")
    own = model.state_dict()
    if set(state) != set(own) or any(tuple(state[k].shape) != tuple(own[k].shape) for k in own):
        shapes = lambda d: {k: tuple(v.shape) for k, v in d.items()}  # noqa: E731
        raise ValueError(f"init checkpoint {path}: its network {shapes(state)} is not this run's {shapes(own)} "
                         "(hidden size and output rank must match)")
    if not np.allclose(np.asarray(ck.get("scale")), scale, rtol=1e-9, atol=0):
        raise ValueError(f"init checkpoint {path}: trained on other training poses (its output scale differs); "
                         "start from a run on this dataset and split")
    model.load_state_dict(state)
    return hashlib.sha256(data).hexdigest()[:16]


def _to_weights(state: dict[str, Any], scale: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                anchor: np.ndarray | None = None) -> KsnnWeights:
    """Fold the per-axis output scale into W2, b2 and return float64 weights in the predictor's layout.

    With ``anchor`` the bias is -f(anchor) without bias (computed in float64), so the exported KSNN is zero there.
    """
    W1 = state["W1"].detach().double().numpy()
    b1 = state["b1"].detach().double().numpy()[:, 0, :]
    if "C" in state:  # an output layer of lower rank, exported as its product
        W2 = np.matmul(state["C"].detach().double().numpy(), state["U"].detach().double().numpy())
    else:
        W2 = state["W2"].detach().double().numpy()
    W2 = W2 * scale[:, None, None]
    if anchor is None:
        b2 = state["b2"].detach().double().numpy()[:, 0, :] * scale[:, None]
    else:
        h = np.tanh(np.einsum("a,kah->kh", np.asarray(anchor, dtype=np.float64), W1) + b1)  # (3, H)
        b2 = -np.einsum("kh,khv->kv", h, W2)
    return KsnnWeights(np.asarray(lo, float), np.asarray(hi, float), W1, b1, W2, b2)


def torch_offsets(weights: KsnnWeights, p: np.ndarray) -> np.ndarray:
    """Offsets (B, V, 3) of raw poses (B, A) computed by the PyTorch module (used to check the ONNX export)."""
    import torch

    model = _module(weights.n_actuators, weights.hidden, weights.n_vertices)
    with torch.no_grad():
        model.W1.copy_(torch.from_numpy(weights.W1))
        model.b1.copy_(torch.from_numpy(weights.b1[:, None, :]))
        model.W2.copy_(torch.from_numpy(weights.W2))
        model.b2.copy_(torch.from_numpy(weights.b2[:, None, :]))
        x = torch.from_numpy(weights.normalize(p).astype(np.float32))
        return model(x).numpy().transpose(1, 2, 0)
