"""Vertex-error metrics of a skin predictor on a set of poses, overall and per surface region.

All figures are in micrometres. "Euclidean" errors are per-vertex distances |pred − truth|; their mean, RMS, 99th
percentile and maximum run over every (pose, vertex) pair. ``rmse_per_coordinate_um`` is the RMS of the x, y and
z components separately (not a vertex distance). The maximum is located by dataset pose index, vertex and region.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

UM = 1e6


def _summary(err: np.ndarray) -> dict[str, float]:
    return {"mean_euclidean_um": float(err.mean() * UM), "rms_euclidean_um": float(np.sqrt(np.mean(err ** 2)) * UM),
            "p99_euclidean_um": float(np.percentile(err, 99) * UM), "max_euclidean_um": float(err.max() * UM)}


def surface_errors(predict: Callable[[np.ndarray], np.ndarray], actuators: np.ndarray, offsets: np.ndarray,
                   indices: Sequence[int], region_names: Sequence[str], vertex_region: np.ndarray,
                   chunk: int = 128) -> dict[str, Any]:
    """Errors of ``predict`` (poses (B, A) → offsets (B, V, 3), metres) on dataset poses ``indices``.

    ``offsets`` may be a memmap: poses are read ``chunk`` at a time; only the (P, V) distances are kept.
    """
    idx = np.asarray(indices, dtype=np.int64)
    if idx.size == 0:
        raise ValueError("no poses to evaluate")
    n_vert = offsets.shape[1]
    labels = np.asarray(vertex_region)
    if labels.shape != (n_vert,):
        raise ValueError(f"vertex_region has shape {labels.shape}, expected ({n_vert},)")
    dist = np.empty((len(idx), n_vert), dtype=np.float64)
    sq = np.zeros(3)
    for s in range(0, len(idx), chunk):
        sel = idx[s:s + chunk]
        d = np.asarray(predict(actuators[sel]), dtype=np.float64) - np.asarray(offsets[sel], dtype=np.float64)
        if d.shape != (len(sel), n_vert, 3):
            raise ValueError(f"predictor gives offsets of shape {d.shape[1:]}, dataset has ({n_vert}, 3)")
        dist[s:s + len(sel)] = np.sqrt((d ** 2).sum(axis=-1))
        sq += (d ** 2).sum(axis=(0, 1))
    flat = int(np.argmax(dist))
    pose_k, vertex = divmod(flat, n_vert)
    rmse = np.sqrt(sq / dist.size) * UM
    per_region = {}
    for r, name in enumerate(region_names):
        cols = np.flatnonzero(labels == r)
        if cols.size:
            per_region[str(name)] = {"n_vertices": int(cols.size), **_summary(dist[:, cols])}
    return {
        "n_poses": len(idx), "n_vertices": int(n_vert), **_summary(dist),
        "rmse_per_coordinate_um": {"x": float(rmse[0]), "y": float(rmse[1]), "z": float(rmse[2])},
        "max_at": {"pose_index": int(idx[pose_k]), "vertex": int(vertex),
                   "region": str(region_names[int(labels[vertex])])},
        "per_region": per_region,
    }


def metrics_match(a: Any, b: Any, rel: float = 1e-6, abs_um: float = 1e-3, path: str = "") -> list[str]:
    """Differences between two metric documents (numbers within ``rel`` or ``abs_um``); empty when they match."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}{k}: present in only one")
            else:
                out += metrics_match(a[k], b[k], rel, abs_um, f"{path}{k}.")
        return out
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return [] if abs(a - b) <= max(abs_um, rel * max(abs(a), abs(b))) else [f"{path[:-1]}: {a} vs {b}"]
    return [] if a == b else [f"{path[:-1]}: {a!r} vs {b!r}"]
