"""The error floor of a hidden size: how close any KSNN with H hidden units per axis can come to a set of poses.

A KSNN's offsets along one axis are W2 h(p) + b2 for the V surface vertices: whatever its hidden layer learns, they
lie in an affine subspace of dimension H (the rest anchor only narrows it to a linear one). The best such subspace
for a set of poses, in least squares, is their centred principal components: the part of the offsets outside the
top H components, axis by axis, is a floor under the RMS error any KSNN of that size has on those poses, set by the
output layer's rank and measured before any training. Where the RMS floor of a hidden size already misses a goal,
more data or training cannot meet it; only a larger H can (and the in-cycle solve's cost grows with H²). The mean,
p99 and max of that least-squares fit say where it leaves its error; they are not bounds (a fit aimed at the max
could trade RMS for a lower max), but a network trained on squared error is such a fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

UM = 1e6


def rank_floor(offsets: np.ndarray, ranks: Sequence[int]) -> dict[int, np.ndarray]:
    """Per rank H, the (P, V) Euclidean distances (m) of ``offsets`` (P poses, V vertices, 3) from their
    least-squares fit by an affine subspace of dimension H per axis; their RMS is the least RMS error any KSNN with
    H hidden units per axis can have on these poses."""
    X = np.asarray(offsets, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] < 2:
        raise ValueError(f"offsets must be (P >= 2, V, 3), got shape {X.shape}")
    hs = sorted({int(h) for h in ranks})
    if not hs or hs[0] < 1:
        raise ValueError(f"ranks must be positive integers, got {list(ranks)}")
    sq = {h: np.zeros(X.shape[:2]) for h in hs}
    for k in range(3):
        centred = X[:, :, k] - X[:, :, k].mean(axis=0)
        u, s, vt = np.linalg.svd(centred, full_matrices=False)
        for h in hs:
            r = min(h, s.size)
            sq[h] += (centred - (u[:, :r] * s[:r]) @ vt[:r]) ** 2
    return {h: np.sqrt(v) for h, v in sq.items()}


def floor_summary(dist: np.ndarray, poses: np.ndarray, goal_max_m: float = 1e-3) -> dict[str, Any]:
    """One rank's RMS floor and its least-squares fit's mean, p99 and max (µm), where the max sits (dataset pose
    index, vertex), and how many poses that fit leaves with a vertex beyond ``goal_max_m``."""
    flat = int(np.argmax(dist))
    k, vertex = divmod(flat, dist.shape[1])
    worst = dist.max(axis=1)
    return {"rms_floor_um": float(np.sqrt(np.mean(dist ** 2)) * UM),
            "mean_euclidean_um": float(dist.mean() * UM), "p99_euclidean_um": float(np.percentile(dist, 99) * UM),
            "max_euclidean_um": float(dist.max() * UM), "max_at": {"pose_index": int(poses[k]), "vertex": vertex},
            "poses_beyond_goal": int((worst > goal_max_m).sum()), "goal_max_um": goal_max_m * UM}
