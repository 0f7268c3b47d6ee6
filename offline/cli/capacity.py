"""``likeness offline capacity``: the error floor each hidden size sets on a dataset's poses, before any training."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The dataset, the split, the hidden sizes and an optional predictor to set beside its floor."""
    p.description = ("For each hidden size H, the least RMS surface error any KSNN with H hidden units per axis "
                     "can have on a dataset's poses (their least-squares fit by an H-dimensional affine subspace per "
                     "axis, the rank of the network's output layer), and that fit's mean, p99 and max in µm, where "
                     "the max sits and how many poses it leaves beyond --goal-max-mm. With --predictor, that "
                     "predictor's own errors on the same poses beside the floors.")
    p.add_argument("--dataset", required=True, help="pose dataset folder, or a dataset pack (.npz)")
    p.add_argument("--split", default="all", choices=("train", "validation", "test", "all"),
                   help="poses to measure (default all converged poses)")
    p.add_argument("--hidden", nargs="+", default=["A", "2A", "4A", "6A"],
                   help="hidden sizes: integers or multiples of the actuator count A (default A 2A 4A 6A)")
    p.add_argument("--goal-max-mm", type=float, default=1.0, help="max error goal counted per pose (default 1 mm)")
    p.add_argument("--predictor", default=None, help="an ONNX predictor to evaluate on the same poses")
    p.add_argument("--out", default=None, help="also write the report (JSON, with this command) to this file")


def run(args: argparse.Namespace) -> int:
    """Measure and print JSON."""
    import json
    import tempfile
    from pathlib import Path

    import numpy as np

    from models.errors import ConfigError, UsageError
    from offline.cli.evaluate import _dataset_folder
    from offline.dataset.store import PoseDataset
    from offline.train.capacity import floor_summary, rank_floor
    from offline.train.evaluate import evaluate_predictor
    from offline.train.ksnn import resolve_hidden

    if not args.goal_max_mm > 0:
        raise UsageError(f"--goal-max-mm must be positive, got {args.goal_max_mm}")
    with tempfile.TemporaryDirectory(prefix="likeness-capacity-") as tmp:
        try:
            ds = PoseDataset(_dataset_folder(Path(args.dataset), Path(tmp)))
            hidden = resolve_hidden(args.hidden, len(ds.names))
            poses = ds.usable if args.split == "all" else ds.split(args.split)
            if poses.size < 2:
                raise ValueError(f"{args.dataset}: split {args.split!r} has {poses.size} converged poses; need 2")
            floors = rank_floor(np.asarray(ds.offsets[poses]), hidden)
            out = {"dataset": {"source": args.dataset, "hash": ds.content_hash(), "split": args.split,
                               "poses": int(poses.size), "vertices": int(ds.offsets.shape[1])},
                   "floor": {str(h): floor_summary(floors[h], poses, args.goal_max_mm * 1e-3) for h in hidden}}
            for h in hidden:  # with as many dimensions as poses, any set of poses is fitted exactly: no floor
                if h >= poses.size - 1:
                    out["floor"][str(h)]["note"] = f"H >= poses - 1 ({poses.size}): fitted exactly, says nothing"
            if args.predictor:
                errors = evaluate_predictor(args.predictor, ds, args.split)
                out["predictor"] = {"path": args.predictor, **{k: errors[k] for k in (
                    "rms_euclidean_um", "mean_euclidean_um", "p99_euclidean_um", "max_euclidean_um", "max_at")}}
        except (ValueError, FileNotFoundError) as exc:
            raise ConfigError(str(exc)) from exc
    if args.out:
        import shlex
        import sys

        from models.atomic import write_bytes

        argv = sys.argv[3:] if sys.argv[1:3] == ["offline", "capacity"] else sys.argv[1:]
        out["command"] = "likeness offline capacity " + " ".join(shlex.quote(a) for a in argv)
        write_bytes(args.out, (json.dumps(out, indent=1) + "\n").encode())
    print(json.dumps(out, indent=1))
    return 0
