"""``likeness offline evaluate``: recompute a predictor's test metrics on its dataset and check its report."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The predictor, the dataset, the report to check and the split."""
    p.description = ("Evaluate an ONNX skin predictor on the test split of a pose dataset (mean, RMS, "
                       "p99 and max Euclidean vertex error, per-coordinate RMSE, the region of the max, per-region "
                       "errors) and compare with predictor_report.json (beside the predictor unless --report is "
                       "given). Exit status 1 when the report does not match.")
    p.add_argument("--predictor", required=True, help="predictor ONNX file")
    p.add_argument("--dataset", nargs="+", required=True, help="pose dataset the predictor was trained on: its "
                   "folder, or a dataset pack (.npz from `likeness offline dataset-pack`; unpacked to a temporary "
                   "folder and hash-checked); several are joined in the order given, as `likeness offline "
                   "dataset-merge` joins them, for a predictor trained on a joined dataset")
    p.add_argument("--report", default=None, help="report to check (default: predictor_report.json beside the "
                   "predictor; no check if there is none)")
    p.add_argument("--split", default="test", choices=("train", "validation", "test", "all"),
                   help="split to evaluate when no report is checked (default test; all: every converged pose, "
                   "for a dataset of fresh poses the predictor never saw)")
    p.add_argument("--worst", type=int, default=0, metavar="N",
                   help="also list the N poses of the split with the largest vertex error, worst first (index, "
                   "error, vertex, region); with --split, not with a report check")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads")


def run(args: argparse.Namespace) -> int:
    """Evaluate, compare, print JSON."""
    import json
    import tempfile

    from models.errors import ConfigError
    from offline.cli._common import joined_folder
    from offline.train.evaluate import REPORT_NAME

    report = Path(args.report) if args.report else Path(args.predictor).with_name(REPORT_NAME)
    with tempfile.TemporaryDirectory(prefix="likeness-eval-") as tmp:
        try:
            dataset = joined_folder([Path(d) for d in args.dataset], Path(tmp))
            result = _evaluate(args, report, dataset)
        except (ValueError, FileNotFoundError) as exc:
            raise ConfigError(str(exc)) from exc
    print(json.dumps(result, indent=1))
    return 0 if result.get("matches", True) else 1


def _evaluate(args: argparse.Namespace, report: Path, dataset: Path) -> dict[str, Any]:
    """Check ``report`` when one applies, else the metrics of the asked split."""
    from models.errors import UsageError
    from offline.train.evaluate import check_report, evaluate_predictor, worst_poses

    if args.worst < 0:
        raise UsageError(f"--worst must be a pose count of 0 or more, got {args.worst}")
    if args.report or (report.exists() and args.split == "test"):
        if args.split != "test":
            raise UsageError("--report checks the test split; leave out --split")
        if args.worst:
            raise UsageError("--worst lists the poses of a split evaluated without a report check; give --split")
        return check_report(report, args.predictor, dataset, args.threads)
    result = {"split": args.split, args.split: evaluate_predictor(args.predictor, dataset, args.split, args.threads)}
    if args.worst:
        result["worst_poses"] = worst_poses(args.predictor, dataset, args.split, args.worst, args.threads)
    return result
