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


def worst_poses(predictor: str | Path, dataset: str | Path | PoseDataset, split: str = "test", n: int = 5,
                threads: int = 1) -> list[dict[str, Any]]:
    """The ``n`` converged poses of ``split`` with the largest vertex error, worst first: each pose's index, its
    largest error (µm), that vertex and its region. Where the max sits, and whether another predictor's max sits
    on the same poses, is what the aggregate metrics do not say."""
    import numpy as np

    from models.predictor import SkinPredictor

    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    ds = dataset if isinstance(dataset, PoseDataset) else PoseDataset(dataset)
    sp = SkinPredictor(predictor, threads=threads)
    names, labels = regions(ds)
    poses = np.asarray(ds.usable if split == "all" else ds.split(split), dtype=np.int64)
    if poses.size == 0:
        raise ValueError("no poses to evaluate")
    worst = np.empty(len(poses))
    where = np.empty(len(poses), dtype=np.int64)
    for s in range(0, len(poses), 128):
        sel = poses[s:s + 128]
        d = np.asarray(sp.predict_offsets(ds.actuators[sel]), dtype=np.float64) - np.asarray(ds.offsets[sel])
        dist = np.sqrt((d ** 2).sum(axis=-1))
        where[s:s + len(sel)] = dist.argmax(axis=1)
        worst[s:s + len(sel)] = dist.max(axis=1)
    order = np.argsort(-worst, kind="stable")[:n]
    return [{"pose_index": int(poses[k]), "max_euclidean_um": float(worst[k] * 1e6), "vertex": int(where[k]),
             "region": str(names[labels[where[k]]])} for k in order]


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
