"""``likeness offline capacity``: the error floor each hidden size sets on a dataset's poses, before any training."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The dataset, the split, the hidden sizes and an optional predictor to set beside its floor."""
    p.description = ("For each hidden size H, the least RMS surface error any KSNN with H hidden units per axis "
                     "can have on a dataset's poses (their least-squares fit by an H-dimensional affine subspace per "
                     "axis, the rank of the network's output layer), and that fit's mean, p99 and max in µm, where "
                     "the max sits and how many poses it leaves beyond --goal-max-mm. With --predictor, that "
                     "predictor's own errors on the same poses beside the floors; with --max-aimed, a fit of each "
                     "size aimed at the max; with --project, how those fits (and the predictor) do on other poses.")
    p.add_argument("--dataset", required=True, nargs="+",
                   help="pose dataset folder, or a dataset pack (.npz); several are joined in the order given")
    p.add_argument("--split", default="all", choices=("train", "validation", "test", "all"),
                   help="poses to measure (default all converged poses)")
    p.add_argument("--hidden", nargs="+", default=["A", "2A", "4A", "6A"],
                   help="hidden sizes: integers or multiples of the actuator count A (default A 2A 4A 6A)")
    p.add_argument("--goal-max-mm", type=float, default=1.0, help="max error goal counted per pose (default 1 mm)")
    p.add_argument("--predictor", default=None, help="an ONNX predictor to evaluate on the same poses")
    p.add_argument("--max-aimed", type=int, default=0, metavar="ROUNDS",
                   help="also fit each size's subspace aimed at the max error (poses and vertices reweighted by "
                   "their largest error for ROUNDS rounds, the best kept): whether a fit of that size meets the "
                   "max goal where least squares does not (default 0: least squares only)")
    p.add_argument("--project", nargs="+", default=None, metavar="DATASET",
                   help="datasets or packs (joined in order, all converged poses) fitted by the subspaces found on "
                   "--dataset's poses, never fitted on: how far the best output layer of each size carries to "
                   "fresh poses")
    p.add_argument("--out", default=None, help="also write the report (JSON, with this command) to this file")


def run(args: argparse.Namespace) -> int:
    """Measure and print JSON."""
    import json
    import tempfile
    from pathlib import Path
    from typing import Any

    import numpy as np

    from models.errors import ConfigError, UsageError
    from offline.cli._common import joined_folder
    from offline.dataset.store import PoseDataset
    from offline.train.capacity import fit_subspaces, fitted, floor_summary, max_aimed_fit, rank_floor, strain_summary
    from offline.train.evaluate import evaluate_predictor
    from offline.train.ksnn import resolve_hidden

    if not args.goal_max_mm > 0:
        raise UsageError(f"--goal-max-mm must be positive, got {args.goal_max_mm}")
    if args.max_aimed < 0:
        raise UsageError(f"--max-aimed must be zero or a positive number of rounds, got {args.max_aimed}")
    goal = args.goal_max_mm * 1e-3
    with tempfile.TemporaryDirectory(prefix="likeness-capacity-") as tmp:
        try:
            ds = PoseDataset(joined_folder([Path(d) for d in args.dataset], Path(tmp) / "dataset"))
            hidden = resolve_hidden(args.hidden, len(ds.names))
            poses = ds.usable if args.split == "all" else ds.split(args.split)
            if poses.size < 2:
                raise ValueError(f"{args.dataset}: split {args.split!r} has {poses.size} converged poses; need 2")
            floors = rank_floor(np.asarray(ds.offsets[poses]), hidden)
            source = args.dataset[0] if len(args.dataset) == 1 else list(args.dataset)
            out = {"dataset": {"source": source, "hash": ds.content_hash(), "split": args.split,
                               "poses": int(poses.size), "vertices": int(ds.offsets.shape[1])},
                   "floor": {str(h): floor_summary(floors[h], poses, goal) for h in hidden}}
            fresh = None
            if args.project:
                pds = PoseDataset(joined_folder([Path(d) for d in args.project], Path(tmp) / "project"))
                fresh = (np.asarray(pds.offsets[pds.usable]), pds.usable)
                if fresh[0].shape[1:] != ds.offsets.shape[1:]:
                    raise ValueError(f"--project poses have {fresh[0].shape[1]} vertices, --dataset "
                                     f"{ds.offsets.shape[1]}: not the same surface")
                out["project"] = {"sources": list(args.project), "hash": pds.content_hash(),
                                  "poses": int(pds.usable.size), "least_squares": {}}
            X = np.asarray(ds.offsets[poses])

            def projected(fit: Any) -> dict[str, Any]:  # the fresh poses by a fit's subspaces: distances, strain
                approx = fitted(fresh[0], fit)
                dist = np.sqrt(((approx - fresh[0]) ** 2).sum(axis=-1))
                return {**floor_summary(dist, fresh[1], goal),
                        **strain_summary(pds.base_vertices, pds.faces, approx, fresh[0])}

            for h in hidden:
                if fresh is not None:
                    out["project"]["least_squares"][str(h)] = projected(fit_subspaces(X, h))
                if args.max_aimed:
                    fit, dist, round_ = max_aimed_fit(X, h, args.max_aimed)
                    out.setdefault("max_aimed", {"rounds": args.max_aimed})[str(h)] = {
                        **floor_summary(dist, poses, goal), "round": round_}
                    if fresh is not None:
                        out["project"].setdefault("max_aimed", {})[str(h)] = projected(fit)
            for h in hidden:  # with as many dimensions as poses, any set of poses is fitted exactly: no floor
                if h >= poses.size - 1:
                    out["floor"][str(h)]["note"] = f"H >= poses - 1 ({poses.size}): fitted exactly, says nothing"
            if args.predictor:
                errors = evaluate_predictor(args.predictor, ds, args.split)
                out["predictor"] = {"path": args.predictor, **{k: errors[k] for k in (
                    "rms_euclidean_um", "mean_euclidean_um", "p99_euclidean_um", "max_euclidean_um", "max_at")}}
                if fresh is not None:
                    errors = evaluate_predictor(args.predictor, pds, "all")
                    out["project"]["predictor"] = {**{k: errors[k] for k in (
                        "rms_euclidean_um", "mean_euclidean_um", "p99_euclidean_um", "max_euclidean_um", "max_at")},
                        "strain_p99_abs": errors["surface_strain"]["p99_abs"]}
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
