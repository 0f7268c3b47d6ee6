"""Evaluate an exported predictor on a dataset split, and check it against the predictor's report.

The training pipeline writes its test metrics with :func:`evaluate_predictor`; ``likeness offline evaluate``
calls the same function on the ONNX file and the dataset folder and compares, so a report can be reproduced.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from models.errors import SpecError
from offline.dataset.describe import regions
from offline.dataset.store import PoseDataset
from offline.train.metrics import metrics_match, surface_errors

REPORT_NAME = "predictor_report.json"
REPORT_FORMAT = "likeness-predictor-report"


def evaluate_predictor(predictor: str | Path, dataset: str | Path | PoseDataset, split: str = "test",
                       threads: int = 1) -> dict[str, Any]:
    """Metrics (see :mod:`offline.train.metrics`) of the ONNX ``predictor`` on the converged poses of ``split``.

    ``split="all"`` takes every converged pose: for a dataset of fresh poses the predictor never saw.
    """
    from models.predictor import SkinPredictor

    ds = dataset if isinstance(dataset, PoseDataset) else PoseDataset(dataset)
    sp = SkinPredictor(predictor, threads=threads)
    if tuple(sp.actuator_names) != tuple(ds.names):
        raise SpecError(str(predictor), "actuators", f"differ from the dataset's {list(ds.names)}",
                        list(sp.actuator_names))
    if sp.n_vertices != ds.offsets.shape[1]:
        raise SpecError(str(predictor), "n_vertices", f"dataset has {ds.offsets.shape[1]} surface vertices",
                        sp.n_vertices)
    names, labels = regions(ds)
    poses = ds.usable if split == "all" else ds.split(split)
    return surface_errors(sp.predict_offsets, ds.actuators, ds.offsets, poses, names, labels,
                          base=ds.base_vertices, faces=ds.faces)


def check_report(report_path: str | Path, predictor: str | Path, dataset: str | Path,
                 threads: int = 1) -> dict[str, Any]:
    """Recompute the test metrics and compare with ``report_path``: returns metrics, match and differences."""
    path = Path(report_path)
    try:
        report = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise SpecError(str(path), "file", "report not found") from exc
    except json.JSONDecodeError as exc:
        raise SpecError(str(path), "json", f"not valid JSON: {exc}") from exc
    if report.get("format") != REPORT_FORMAT:
        raise SpecError(str(path), "format", "not a predictor report with test metrics (reports from before the "
                        "train / validation / test splits have none): regenerate it as docs/predictor.md shows, or "
                        "evaluate fresh poses with --split all, which checks no report",
                        report.get("format"))
    ds = PoseDataset(dataset)
    digest = ds.content_hash()
    test = evaluate_predictor(predictor, ds, "test", threads)
    diffs = []
    if report["dataset"].get("hash") != digest:
        diffs.append(f"dataset.hash: report {report['dataset'].get('hash')} vs dataset {digest}")
    diffs += metrics_match(report["test"], test)
    return {"report": str(path), "dataset": {"id": ds.id, "hash": digest}, "test": test, "matches": not diffs,
            "differences": diffs}
