"""Whether a predictor's worst poses have other FEM equilibria: solve each again from other starts and compare.

A skin with several equilibria at a pose gives that pose a label that depends on where its solve started; a network
trained on labels from other starts would then read as wrong where it is not. For the ``--poses`` poses of a
dataset (folder or pack) with the most triangles whose strain error exceeds ``--strain`` under the predictor,
this solves each pose on the head's FEM (quadratic tets) three ways — from rest, along a path (the pose at half
its values first, then the pose from that state), and from the state of the dataset's nearest other pose (itself
solved from rest) — and writes, per pose and start, how far the solution lies from the stored label (surface
distance, principal-strain difference) beside the predictor's strain error and largest vertex error against the
label and against that solution. ``--pose-index`` names the poses instead (the dataset's own indices, e.g. a split's
worst poses from ``likeness offline evaluate --worst``). Run from the repository root::

    python -m tools.fem_branches --config heads/sample/head.toml --mesh heads/sample/skin \\
        --dataset heads/sample/predictor_fresh.npz --predictor heads/sample/predictor.onnx --poses 8 \\
        --out docs/predictor_capacity/fem_branches_fresh.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

_PROBLEM: Any = None


def _solve(job: tuple[Any, int, str, np.ndarray, np.ndarray | None]) -> tuple[int, str, np.ndarray, bool, float]:
    """One pose from one start, in a worker that builds the FEM problem once."""
    global _PROBLEM
    spec, k, how, p, neighbour = job
    if _PROBLEM is None:
        _PROBLEM = spec.build()
    t0 = time.perf_counter()
    if how == "path":
        warm = _PROBLEM.solve(0.5 * p, None).state
    elif how == "nearest":
        warm = _PROBLEM.solve(neighbour, None).state
    else:
        warm = None
    r = _PROBLEM.solve(p, warm)
    return k, how, np.asarray(r.surface, dtype=np.float64), bool(r.converged), time.perf_counter() - t0


def _strain_error(base: np.ndarray, faces: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from models.predictor import surface_principal_stretches

    return np.abs(surface_principal_stretches(base, faces, a) - surface_principal_stretches(base, faces, b)).max(-1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--dataset", required=True, help="pose dataset folder or pack (its labels are judged)")
    ap.add_argument("--predictor", required=True)
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--pose-index", type=int, nargs="+", default=None,
                    help="solve these dataset poses (indices into the dataset) instead of the --poses worst")
    ap.add_argument("--strain", type=float, default=0.02, help="strain error that counts a triangle (default 0.02)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    from models.headspec import load_head
    from models.predictor import SkinPredictor
    from offline.cli._common import dataset_folder
    from offline.dataset.fem_problem import FemSpec, material_fields
    from offline.dataset.store import PoseDataset
    from offline.guard_reports import write_json
    from offline.strain_eval import file_hash

    head = load_head(args.config)
    spec = FemSpec(config=args.config, mesh=args.mesh, linkmap=str(head.path("linkmap")), element_order=2,
                   **material_fields(head.skin_material()))
    with tempfile.TemporaryDirectory(prefix="likeness-branches-") as tmp:
        ds = PoseDataset(dataset_folder(Path(args.dataset), Path(tmp)))
        idx = ds.usable
        P = ds.actuators[idx]
        labels = ds.base_vertices + np.asarray(ds.offsets[idx], dtype=np.float64)
        dataset_hash = ds.content_hash()
        base, faces = ds.base_vertices, ds.faces
    pred = SkinPredictor(args.predictor)
    net = base + np.asarray(pred.predict_offsets(P), dtype=np.float64)
    err = np.array([_strain_error(base, faces, net[k], labels[k]) for k in range(len(idx))])
    if args.pose_index is None:
        worst = np.argsort(-(err > args.strain).sum(axis=1), kind="stable")[:args.poses]
    else:
        where = {int(i): k for k, i in enumerate(idx)}
        missing = [i for i in args.pose_index if i not in where]
        if missing:
            ap.error(f"--pose-index {missing}: not the 0-based index of a converged pose of {args.dataset}")
        worst = np.array([where[i] for i in args.pose_index])
    span = np.array([a.max - a.min for a in head.actuators])
    jobs = []
    for k in worst:
        d = np.abs((P - P[k]) / span).sum(axis=1)
        d[k] = np.inf
        for how in ("rest", "path", "nearest"):
            jobs.append((spec, int(k), how, P[k], P[int(np.argmin(d))]))
    solved: dict[int, dict[str, tuple[np.ndarray, bool, float]]] = {}
    with ProcessPoolExecutor(args.workers) as ex:
        for k, how, surf, conv, secs in ex.map(_solve, jobs):
            solved.setdefault(k, {})[how] = (surf, conv, secs)
    rows = []
    for k in worst:
        row: dict[str, Any] = {"pose_index": int(idx[k]), "triangles_over": int((err[k] > args.strain).sum()),
                               "predictor_vs_label_p99": float(np.percentile(err[k], 99)),
                               "predictor_max_distance_to_label_mm": float(
                                   np.linalg.norm(net[k] - labels[k], axis=1).max() * 1e3)}
        for how, (surf, conv, secs) in solved[int(k)].items():
            vs_label = _strain_error(base, faces, surf, labels[k])
            row[how] = {"converged": conv, "seconds": secs,
                        "max_distance_to_label_mm": float(np.linalg.norm(surf - labels[k], axis=1).max() * 1e3),
                        "max_strain_difference_to_label": float(vs_label.max()),
                        "triangles_over_vs_label": int((vs_label > args.strain).sum()),
                        "predictor_vs_this_p99": float(np.percentile(_strain_error(base, faces, net[k], surf), 99)),
                        "predictor_max_distance_to_this_mm": float(np.linalg.norm(net[k] - surf, axis=1).max() * 1e3)}
        rows.append(row)
    other = [r["pose_index"] for r in rows
             if any(r[h]["max_distance_to_label_mm"] > 0.01 for h in ("rest", "path", "nearest"))]
    report = {"command": "python -m tools.fem_branches " + " ".join(sys.argv[1:] if argv is None else argv),
              "inputs": {"config": {"path": args.config, "sha256": file_hash(args.config)},
                         "predictor": {"path": args.predictor, "sha256": file_hash(args.predictor)},
                         "dataset": {"path": args.dataset, "content_hash": dataset_hash}},
              "settings": {"poses": args.poses, "pose_index": args.pose_index, "strain": args.strain,
                           "element_order": 2},
              "poses_with_another_equilibrium": other, "poses": rows}
    write_json(args.out, report)
    print(f"{len(rows)} poses; another equilibrium (> 0.01 mm from the label) at {other or 'none'} -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
