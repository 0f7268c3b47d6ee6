"""``likeness offline sweep``: one actuator swept from a dataset's pose, solved from rest, beside predictors."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head and its skin, the pose to start from, the actuator and its sweep, the vertex and the predictors."""
    p.description = ("Move one actuator of a dataset's pose evenly across part of its range, solve every point from "
                     "rest with the skin problem (a resumable dataset folder) and print, at one surface vertex, the "
                     "solved offset and each predictor's, with the largest change between neighbouring points of "
                     "each: whether the skin changes abruptly where a predictor errs, or the predictor does.")
    from offline.cli._common import add_skin_problem_arguments

    add_skin_problem_arguments(p)
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: CPU count)")
    p.add_argument("--dataset", required=True, help="pose dataset folder holding the pose to start from")
    p.add_argument("--pose", type=int, required=True, help="index of that pose in the dataset")
    p.add_argument("--actuator", required=True, help="name of the actuator to sweep")
    p.add_argument("--from", dest="frm", type=float, default=None,
                   help="start, as a fraction of the actuator's range (default: the pose's own value)")
    p.add_argument("--to", type=float, required=True, help="end, as a fraction of the actuator's range")
    p.add_argument("--steps", type=int, default=11, help="points of the sweep, ends included (default 11)")
    p.add_argument("--vertex", type=int, required=True, help="surface vertex to read")
    p.add_argument("--predictor", nargs="*", default=[], help="ONNX predictors to read beside the solved skin")
    p.add_argument("--out", required=True, help="folder of the solved sweep (created, or resumed)")
    p.add_argument("--quiet", action="store_true", help="no progress line")


def run(args: argparse.Namespace) -> int:
    """Solve the sweep and print its report as JSON."""
    import json
    import sys

    import numpy as np

    from models.errors import UsageError
    from offline.dataset.build import DatasetSettings
    from offline.dataset.store import PoseDataset
    from offline.dataset.sweep import solve_sweep, sweep_poses, sweep_report

    source = PoseDataset(args.dataset)
    if args.actuator not in source.names:
        raise UsageError(f"--actuator {args.actuator!r} is not an actuator of {args.dataset} "
                         f"({', '.join(source.names)})")
    if not 0 <= args.pose < len(source.actuators):
        raise UsageError(f"--pose {args.pose} is not a pose of {args.dataset} (0 to {len(source.actuators) - 1})")
    index = list(source.names).index(args.actuator)
    poses = sweep_poses(np.asarray(source.actuators[args.pose], float), index, source.lo, source.hi, args.to,
                        args.steps, args.frm)
    settings = DatasetSettings(config=args.config, out=args.out, poses=len(poses), mesh=args.mesh,
                               linkmap=args.linkmap, synthetic=args.synthetic, workers=args.workers,
                               element_order=args.element_order, backend=args.backend, start="rest")
    ds = solve_sweep(settings, poses, progress_stream=None if args.quiet else sys.stderr)
    report = {"command": " ".join(["likeness", *sys.argv[1:]]),
              "dataset": {"source": args.dataset, "hash": source.content_hash(), "pose": args.pose},
              "actuator": args.actuator, "vertex": args.vertex,
              **sweep_report(ds, index, args.vertex, args.predictor)}
    print(json.dumps(report, indent=1))
    return 0
