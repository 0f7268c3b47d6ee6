"""Vertex-error metrics of a skin predictor on a set of poses, overall and per surface region.

All figures are in micrometres. "Euclidean" errors are per-vertex distances |pred − truth|; their mean, RMS, 99th
percentile and maximum run over every (pose, vertex) pair. ``rmse_per_coordinate_um`` is the RMS of the x, y and
z components separately (not a vertex distance). The maximum is located by dataset pose index, vertex and region.

With the base surface and its triangles given, ``surface_strain`` compares the principal in-plane engineering
strains (stretch − 1, per triangle, against the base surface) of the predicted surface with the FEM's: the runtime's
strain guard reads strain off the prediction, and sub-millimetre vertex errors on millimetre triangles can make
large false strains. Its figures are absolute strain differences (0.02 = 2 % strain), over every (pose, triangle)
pair, taking for each the larger of the two principal differences.
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
                   chunk: int = 128, base: np.ndarray | None = None,
                   faces: np.ndarray | None = None) -> dict[str, Any]:
    """Errors of ``predict`` (poses (B, A) → offsets (B, V, 3), metres) on dataset poses ``indices``.

    ``offsets`` may be a memmap: poses are read ``chunk`` at a time; only the (P, V) distances are kept (and the
    (P, T) strain differences when ``base`` and ``faces`` are given).
    """
    idx = np.asarray(indices, dtype=np.int64)
    if idx.size == 0:
        raise ValueError("no poses to evaluate")
    n_vert = offsets.shape[1]
    labels = np.asarray(vertex_region)
    if labels.shape != (n_vert,):
        raise ValueError(f"vertex_region has shape {labels.shape}, expected ({n_vert},)")
    dist = np.empty((len(idx), n_vert), dtype=np.float64)
    with_strain = base is not None and faces is not None and len(faces) > 0
    strain_err = np.empty((len(idx), len(faces)), dtype=np.float64) if with_strain else None
    fem_strain_max = 0.0
    sq = np.zeros(3)
    for s in range(0, len(idx), chunk):
        sel = idx[s:s + chunk]
        truth = np.asarray(offsets[sel], dtype=np.float64)
        pred = np.asarray(predict(actuators[sel]), dtype=np.float64)
        d = pred - truth
        if d.shape != (len(sel), n_vert, 3):
            raise ValueError(f"predictor gives offsets of shape {d.shape[1:]}, dataset has ({n_vert}, 3)")
        dist[s:s + len(sel)] = np.sqrt((d ** 2).sum(axis=-1))
        sq += (d ** 2).sum(axis=(0, 1))
        if strain_err is not None:
            from models.predictor import surface_principal_stretches

            e_pred = surface_principal_stretches(base, faces, base + pred)
            e_fem = surface_principal_stretches(base, faces, base + truth)
            strain_err[s:s + len(sel)] = np.abs(e_pred - e_fem).max(axis=-1)
            fem_strain_max = max(fem_strain_max, float(np.nanmax(np.abs(e_fem - 1.0))))
    flat = int(np.argmax(dist))
    pose_k, vertex = divmod(flat, n_vert)
    rmse = np.sqrt(sq / dist.size) * UM
    per_region = {}
    for r, name in enumerate(region_names):
        cols = np.flatnonzero(labels == r)
        if cols.size:
            per_region[str(name)] = {"n_vertices": int(cols.size), **_summary(dist[:, cols])}
    out = {
        "n_poses": len(idx), "n_vertices": int(n_vert), **_summary(dist),
        "rmse_per_coordinate_um": {"x": float(rmse[0]), "y": float(rmse[1]), "z": float(rmse[2])},
        "max_at": {"pose_index": int(idx[pose_k]), "vertex": int(vertex),
                   "region": str(region_names[int(labels[vertex])])},
        "per_region": per_region,
    }
    if strain_err is not None:
        out["surface_strain"] = _strain_summary(strain_err, idx, np.asarray(faces), labels, region_names,
                                                fem_strain_max)
    return out


def _strain_summary(err: np.ndarray, idx: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    region_names: Sequence[str], fem_strain_max: float) -> dict[str, Any]:
    """Principal-strain differences (absolute strain) over (pose, triangle); degenerate triangles are counted."""
    bad = ~np.isfinite(err)
    vals = err[~bad]
    flat = int(np.argmax(np.where(bad, -1.0, err)))
    pose_k, tri = divmod(flat, err.shape[1])
    return {"units": "absolute principal engineering strain difference, predicted vs FEM, per triangle",
            "n_triangles": int(err.shape[1]), "degenerate_triangles": int(bad.any(axis=0).sum()),
            "mean_abs": float(vals.mean()), "p99_abs": float(np.percentile(vals, 99)),
            "max_abs": float(vals.max()), "fem_max_abs_strain": fem_strain_max,
            "max_at": {"pose_index": int(idx[pose_k]), "triangle": tri,
                       "region": str(region_names[int(labels[faces[tri, 0]])])}}


def metrics_match(a: Any, b: Any, rel: float = 1e-6, abs_tol: float = 1e-6, path: str = "") -> list[str]:
    """Differences between two metric documents (numbers within ``rel`` or ``abs_tol``); empty when they match.

    ``abs_tol`` only matters for numbers near zero: 1e-6 µm for distances, 1e-6 for strains.
    """
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}{k}: present in only one")
            else:
                out += metrics_match(a[k], b[k], rel, abs_tol, f"{path}{k}.")
        return out
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return [] if abs(a - b) <= max(abs_tol, rel * max(abs(a), abs(b))) else [f"{path[:-1]}: {a} vs {b}"]
    return [] if a == b else [f"{path[:-1]}: {a!r} vs {b!r}"]
