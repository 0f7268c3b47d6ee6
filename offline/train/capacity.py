"""The error floor of a hidden size: how close any KSNN with H hidden units per axis can come to a set of poses.

A KSNN's offsets along one axis are W2 h(p) + b2 for the V surface vertices: whatever its hidden layer learns, they
lie in an affine subspace of dimension H (the rest anchor only narrows it to a linear one). The best such subspace
for a set of poses, in least squares, is their centred principal components: the part of the offsets outside the
top H components, axis by axis, is a floor under the RMS error any KSNN of that size has on those poses, set by the
output layer's rank and measured before any training. Where the RMS floor of a hidden size already misses a goal,
more data or training cannot meet it; only a larger H can (and the in-cycle solve's cost grows with H²). The mean,
p99 and max of that least-squares fit say where it leaves its error; they are not bounds: a fit aimed at the max
trades RMS for a lower max. :func:`max_aimed_fit` finds such a subspace (poses and vertices reweighted by their
largest error, round by round), so a max goal missed by the least-squares fit is told apart from one no subspace of
that size meets. :func:`project` fits other poses (never fitted on) by a fit's subspaces: how far the best output
layer of that size carries to fresh poses, given perfect hidden features.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
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


@dataclass(frozen=True)
class SubspaceFit:
    """Per axis, an affine subspace (centre (V,), orthonormal basis (V, H) in vertex-weighted coordinates) and the
    vertex weights (V,) that define the fit of a pose: least squares with the squared weights."""

    centres: tuple[np.ndarray, ...]
    bases: tuple[np.ndarray, ...]
    vertex_weights: np.ndarray


def _check(offsets: np.ndarray) -> np.ndarray:
    X = np.asarray(offsets, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] < 2:
        raise ValueError(f"offsets must be (P >= 2, V, 3), got shape {X.shape}")
    return X


def fit_subspaces(offsets: np.ndarray, rank: int, pose_weights: np.ndarray | None = None,
                  vertex_weights: np.ndarray | None = None) -> SubspaceFit:
    """The rank-``rank`` affine subspace per axis minimizing the pose- and vertex-weighted squared error (unit
    weights: the least-squares fit of :func:`rank_floor`)."""
    X = _check(offsets)
    P, V, _ = X.shape
    a = np.ones(P) if pose_weights is None else np.asarray(pose_weights, dtype=np.float64)
    b = np.ones(V) if vertex_weights is None else np.asarray(vertex_weights, dtype=np.float64)
    if a.shape != (P,) or b.shape != (V,) or not (np.all(a > 0) and np.all(b > 0)):
        raise ValueError("pose and vertex weights must be positive, one per pose and per vertex")
    r = min(int(rank), P, V)
    centres, bases = [], []
    for k in range(3):
        Y = X[:, :, k]
        c = (a @ Y) / a.sum()
        Z = (Y - c) * b * np.sqrt(a)[:, None]
        _, vecs = np.linalg.eigh(Z.T @ Z)  # ascending: the top r are the last columns
        centres.append(c)
        bases.append(np.ascontiguousarray(vecs[:, -r:]))
    return SubspaceFit(tuple(centres), tuple(bases), b.copy())


def fitted(offsets: np.ndarray, fit: SubspaceFit) -> np.ndarray:
    """The best fit (vertex-weighted least squares, pose by pose) of ``offsets`` (P, V, 3) within ``fit``'s
    subspaces: what an output layer of that size gives with hidden features that are perfect for these poses."""
    X = np.asarray(offsets, dtype=np.float64)
    b = fit.vertex_weights
    if X.ndim != 3 or X.shape[1:] != (b.size, 3):
        raise ValueError(f"offsets must be (P, {b.size}, 3) to project on this fit, got shape {X.shape}")
    out = np.empty_like(X)
    for k in range(3):
        Yb = (X[:, :, k] - fit.centres[k]) * b
        Q = fit.bases[k]
        out[:, :, k] = fit.centres[k] + ((Yb @ Q) @ Q.T) / b
    return out


def project(offsets: np.ndarray, fit: SubspaceFit) -> np.ndarray:
    """The (P, V) Euclidean distances (m) of ``offsets`` from their best fit within ``fit``'s subspaces."""
    return np.sqrt(((fitted(offsets, fit) - np.asarray(offsets, dtype=np.float64)) ** 2).sum(axis=-1))


def strain_summary(base: np.ndarray, faces: np.ndarray, approx: np.ndarray, offsets: np.ndarray) -> dict[str, float]:
    """Surface-strain error of ``approx`` against ``offsets`` (both (P, V, 3) from ``base``), as the predictor's
    reports measure it: per pose and triangle, the largest absolute difference of the principal stretches."""
    from models.predictor import surface_principal_stretches

    err = np.abs(surface_principal_stretches(base, faces, base + approx)
                 - surface_principal_stretches(base, faces, base + offsets)).max(axis=-1)
    err = err[np.isfinite(err)]
    return {"strain_mean_abs": float(err.mean()), "strain_p99_abs": float(np.percentile(err, 99)),
            "strain_max_abs": float(err.max())}


def max_aimed_fit(offsets: np.ndarray, rank: int, rounds: int = 40) -> tuple[SubspaceFit, np.ndarray, int]:
    """A rank-``rank`` subspace per axis aimed at the largest Euclidean error: starting from least squares, each
    round multiplies every pose's weight by its largest error (over the mean of those) and every vertex's by the
    square root of its own; the fit with the smallest max over ``rounds`` rounds is returned with its (P, V)
    distances and its round (0: least squares). A heuristic: its max is one a subspace of that size reaches, an
    upper bound on the least possible, not the least."""
    X = _check(offsets)
    if rounds < 1:
        raise ValueError(f"rounds must be positive, got {rounds}")
    P, V, _ = X.shape
    a, b = np.ones(P), np.ones(V)
    best: tuple[SubspaceFit, np.ndarray, int] | None = None
    for k in range(rounds):
        fit = fit_subspaces(X, rank, a, b)
        dist = project(X, fit)
        if best is None or dist.max() < best[1].max():
            best = (fit, dist, k)
        worst_pose, worst_vertex = dist.max(axis=1), dist.max(axis=0)
        if not worst_pose.max() > 0:
            break
        a = a * np.maximum(worst_pose / worst_pose.mean(), 1e-6)
        a /= a.mean()
        b = b * np.sqrt(np.maximum(worst_vertex / worst_vertex.mean(), 1e-6))
        b /= b.mean()
    assert best is not None
    return best
