"""Discretization refinement study of the skin FEM: how much the outer surface moves when the mesh gets finer.

Levels (each keeps the shipped mesh's nodes first, in order, so solutions compare at the same material points):

- ``L0``: the shipped linear mesh; ``P2``: the same tets with mid-edge nodes (quadratic, :func:`to_quadratic`);
- ``L1``: every tet split 1:8 (:func:`refine_uniform`); ``L1P2``: L1 quadratic; ``L2``: L1 split 1:8 again.

For each pose and each pair of successive levels the study reports the change of the outer-surface displacement at
the shipped mesh's outer vertices (mean, p99, max Euclidean, the region of the max, and the change relative to the
displacement). Pure functions here; :mod:`offline.refinement_study` runs them resumably.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

#: Every level the study knows, coarsest first (the default order of successive comparisons).
LEVELS: tuple[str, ...] = ("L0", "P2", "L1", "L1P2", "L2")
#: Below this largest displacement (m) a pose counts as at rest: relative changes are not reported for it.
MIN_DISPLACEMENT = 1e-6


def build_levels(mesh: Any, outer: np.ndarray, triangles: np.ndarray, names: Sequence[str]) -> dict[str, Any]:
    """The meshes of the named levels (see module doc), built from the shipped linear mesh ``mesh``.

    ``outer``/``triangles`` are the shipped outer surface (mesh numbering); every level keeps those node indices.
    """
    from offline.fem import to_quadratic
    from offline.strain_eval import refine_uniform

    unknown = [n for n in names if n not in LEVELS]
    if unknown:
        raise ValueError(f"unknown refinement level(s) {unknown}; known: {', '.join(LEVELS)}")
    if mesh.order != 1:
        raise ValueError(f"the study starts from a linear mesh; got element order {mesh.order}")
    out: dict[str, Any] = {}
    l1 = l1_outer = l1_tris = None
    for name in names:
        if name == "L0":
            out[name] = mesh
        elif name == "P2":
            out[name] = to_quadratic(mesh)
        else:
            if l1 is None:
                l1, l1_outer, l1_tris = refine_uniform(mesh, outer, triangles)
            if name == "L1":
                out[name] = l1
            elif name == "L1P2":
                out[name] = to_quadratic(l1)
            else:
                out[name] = refine_uniform(l1, l1_outer, l1_tris)[0]
    return out


def representative_poses(head: Any, n: int, seed: int = 0) -> tuple[np.ndarray, list[str]]:
    """``n`` poses (n, A) SI with labels: neutral, jaw fully open, left smile, right smile, then random poses from
    the head's sampler (``sample_poses`` with ``seed``), as many as ``n`` asks for."""
    from offline.dataset.sampling import sample_poses

    if n < 1:
        raise ValueError(f"number of poses must be positive, got {n}")
    acts = head.actuators
    names = [a.name for a in acts]
    neutral = np.array([a.neutral for a in acts], dtype=np.float64)
    fixed: list[tuple[str, np.ndarray]] = [("neutral", neutral)]

    def at_max(label: str, which: Sequence[str]) -> None:
        if all(w in names for w in which):
            p = neutral.copy()
            for w in which:
                p[names.index(w)] = acts[names.index(w)].max
            fixed.append((label, p))

    at_max("jaw_open", ["jaw"])
    at_max("smile_l", ["lip_corner_l_up", "lip_corner_l_back"])
    at_max("smile_r", ["lip_corner_r_up", "lip_corner_r_back"])
    fixed = fixed[:n]
    poses = [p for _, p in fixed]
    labels = [lab for lab, _ in fixed]
    if n > len(fixed):
        rnd = sample_poses(head, n - len(fixed), seed=seed)
        poses.extend(rnd)
        labels.extend(f"random_{k}" for k in range(len(rnd)))
    return np.array(poses), labels


def compare_displacements(coarse: np.ndarray, fine: np.ndarray, region_names: Sequence[str],
                          labels: np.ndarray) -> dict[str, Any]:
    """Change from the coarse to the fine surface displacement (both (V, 3), m, at the same vertices).

    Returns mean, p99 and max Euclidean change (m), the vertex and region of the max, the fine displacement's
    mean and max magnitude, the change relative to them (mean/mean, max/max, and the largest per-vertex ratio
    over vertices moving at least 10 % of the largest displacement; None for a pose at rest), and per region the
    mean and max change.
    """
    a = np.asarray(coarse, dtype=np.float64)
    b = np.asarray(fine, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"displacements must both be (V, 3); got {a.shape} and {b.shape}")
    labels = np.asarray(labels)
    if labels.shape != (len(a),):
        raise ValueError(f"region labels must be ({len(a)},); got {labels.shape}")
    d = np.linalg.norm(b - a, axis=1)
    mag = np.linalg.norm(b, axis=1)
    k = int(np.argmax(d))
    moves = mag.max() > MIN_DISPLACEMENT
    big = mag >= 0.1 * mag.max() if moves else np.zeros(len(mag), dtype=bool)
    per_region = {}
    for r, name in enumerate(region_names):
        m = labels == r
        if m.any():
            per_region[name] = {"vertices": int(m.sum()), "mean_m": float(d[m].mean()), "max_m": float(d[m].max())}
    return {
        "mean_m": float(d.mean()), "p99_m": float(np.percentile(d, 99)), "max_m": float(d[k]),
        "max_vertex": k, "max_region": str(region_names[int(labels[k])]),
        "displacement_mean_m": float(mag.mean()), "displacement_max_m": float(mag.max()),
        "relative_mean": float(d.mean() / mag.mean()) if moves else None,
        "relative_max": float(d.max() / mag.max()) if moves else None,
        "relative_max_pointwise": float((d[big] / mag[big]).max()) if big.any() else None,
        "per_region": per_region,
    }


def summarize(pairs: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any]:
    """Over the poses of each level pair: mean of the per-pose means, largest p99 and max (with pose and region)."""
    out = {}
    for pair, rows in pairs.items():
        rows = [r for r in rows if r is not None]
        if not rows:
            continue
        worst = max(rows, key=lambda r: r["max_m"])
        out[pair] = {"poses": len(rows), "mean_m": float(np.mean([r["mean_m"] for r in rows])),
                     "p99_max_m": float(max(r["p99_m"] for r in rows)), "max_m": worst["max_m"],
                     "max_pose": worst.get("pose"), "max_region": worst["max_region"],
                     "relative_mean": _mean_or_none([r["relative_mean"] for r in rows]),
                     "relative_max": _max_or_none([r["relative_max"] for r in rows])}
    return out


def _mean_or_none(values: Sequence[float | None]) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None


def _max_or_none(values: Sequence[float | None]) -> float | None:
    v = [x for x in values if x is not None]
    return float(max(v)) if v else None
