"""A sweep of one actuator from a dataset's pose, solved by the skin problem and read beside predictors at one vertex.

Where a predictor is far off on a pose, the sweep tells whether the skin itself changes abruptly there (its largest
change between neighbouring sweep points against the others) or the predictor does. Each point is solved from rest,
so its label does not depend on the order points finish in (a skin with several equilibria takes the rest branch).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from models.errors import UsageError
from offline.dataset.build import DatasetSettings, problem_spec
from offline.dataset.store import PoseDataset


def sweep_poses(start: np.ndarray, index: int, lo: np.ndarray, hi: np.ndarray, to: float, steps: int,
                frm: float | None = None) -> np.ndarray:
    """(steps, A) poses: ``start`` with actuator ``index`` moved evenly from fraction ``frm`` of its range (default:
    where ``start`` has it) to fraction ``to``."""
    if steps < 2:
        raise UsageError(f"--steps must be at least 2, got {steps}")
    span = hi[index] - lo[index]
    first = (start[index] - lo[index]) / span if frm is None else frm
    for name, x in (("--from", first), ("--to", to)):
        if not 0.0 <= x <= 1.0:
            raise UsageError(f"{name} must be a fraction of the actuator's range in [0, 1], got {x}")
    poses = np.repeat(np.asarray(start, float)[None], steps, axis=0)
    poses[:, index] = lo[index] + np.linspace(first, to, steps) * span
    return poses


def solve_sweep(settings: DatasetSettings, poses: np.ndarray, progress_stream: TextIO | None = sys.stderr
                ) -> PoseDataset:
    """Solve ``poses`` from rest into the (resumable) dataset folder ``settings.out``."""
    from models.headspec import load_head
    from offline.dataset.generate import generate_dataset
    from offline.engine import make_engine

    head = load_head(settings.config)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    spec = problem_spec(settings, head, lo, hi)
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    with make_engine(settings.engine, settings.workers, settings.threads_per_worker) as engine:
        generate_dataset(settings.out, spec, poses, head=head.name, names=head.actuator_names, units=units, lo=lo,
                         hi=hi, engine=engine, seed=0, sampling={"sweep": True}, progress_stream=progress_stream,
                         rest_pose=None if settings.synthetic else head.neutral_pose, start="rest")
    return PoseDataset(settings.out)


def _largest_step(values: np.ndarray) -> float:
    """The largest Euclidean change between neighbouring points of a (steps, 3) track."""
    return float(np.linalg.norm(np.diff(values, axis=0), axis=1).max()) if len(values) > 1 else 0.0


def sweep_report(ds: PoseDataset, index: int, vertex: int, predictors: Sequence[str | Path]) -> dict[str, Any]:
    """Per converged sweep point: the actuator's fraction of its range, the solved offset of ``vertex`` and each
    predictor's, in mm; per track its largest change between neighbouring points, and each predictor's largest
    error."""
    from models.predictor import SkinPredictor

    if not 0 <= vertex < ds.offsets.shape[1]:
        raise UsageError(f"--vertex {vertex} is not a surface vertex (0 to {ds.offsets.shape[1] - 1})")
    pts = ds.usable
    frac = (ds.actuators[pts, index] - ds.lo[index]) / (ds.hi[index] - ds.lo[index])
    fem = np.asarray(ds.offsets[pts][:, vertex, :], float)
    out: dict[str, Any] = {"points": int(pts.size), "not_converged": int(len(ds.actuators) - pts.size),
                           "fraction": [round(float(f), 6) for f in frac],
                           "solved_mm": (fem * 1e3).round(4).tolist(),
                           "solved_largest_step_mm": round(_largest_step(fem) * 1e3, 4), "predictors": {}}
    for path in predictors:
        sp = SkinPredictor(path)
        if sp.n_vertices != ds.offsets.shape[1]:
            raise UsageError(f"{path}: {sp.n_vertices} surface vertices, the skin has {ds.offsets.shape[1]}")
        pred = np.asarray(sp.predict_offsets(ds.actuators[pts])[:, vertex, :], float)
        err = np.linalg.norm(pred - fem, axis=1)
        out["predictors"][str(path)] = {"predicted_mm": (pred * 1e3).round(4).tolist(),
                                        "largest_step_mm": round(_largest_step(pred) * 1e3, 4),
                                        "error_mm": (err * 1e3).round(4).tolist(),
                                        "max_error_mm": round(float(err.max()) * 1e3, 4)}
    return out
