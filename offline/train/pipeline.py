"""Dataset → KSNN → ONNX → ``predictor_report.json``, with train / validation / test kept apart.

Training reads the dataset's train split; early stopping, the best epoch and the hidden size are chosen on the
validation split only; the exported predictor is evaluated once on the test split for the report. Outputs in
``out``: ``predictor.onnx`` (float32), optionally ``predictor_int8.onnx``, ``predictor_report.json`` (written
whole, see ``docs/predictor.md``), ``vertex_error.png`` (mean test error per surface vertex),
``training_curves.png``, and ``checkpoints/`` so training resumes.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from offline.dataset.describe import material_info, mesh_info, regions
from offline.dataset.splits import SPLIT_NAMES
from offline.dataset.store import PoseDataset
from offline.train.evaluate import REPORT_FORMAT, REPORT_NAME, evaluate_predictor
from offline.train.export import export_int8, export_predictor, predictor_metadata
from offline.train.ksnn import TrainConfig, TrainResult, resolve_hidden, train_ksnn
from offline.train.metrics import surface_errors

REPORT_VERSION = 1
SELECTION = ("hidden size: lowest validation objective (MSE of per-axis scaled offsets, plus edge_weight x the "
             "edge-strain MSE when edge_weight > 0); epoch: best validation objective with early stopping on "
             "validation; the test split plays no part in either")


def _numpy_predict(weights) -> Callable[[np.ndarray], np.ndarray]:
    def predict(p: np.ndarray) -> np.ndarray:
        x = weights.normalize(p)
        h = np.tanh(np.einsum("ba,kah->kbh", x, weights.W1) + weights.b1[:, None, :])
        return (np.einsum("kbh,khv->kbv", h, weights.W2) + weights.b2[:, None, :]).transpose(1, 2, 0)

    return predict


def train_pipeline(dataset_dir: str | Path, out_dir: str | Path, config: TrainConfig | None = None,
                   hidden: Sequence[int | str] | None = None, int8: bool = False,
                   log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the whole training for one dataset folder; returns the report (also written to predictor_report.json)."""
    t0 = time.perf_counter()
    config = config or TrainConfig()
    ds = PoseDataset(dataset_dir)
    out = Path(out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    train_idx, val_idx, test_idx = (ds.split(name) for name in SPLIT_NAMES)
    for name, idx, need in (("train", train_idx, 2), ("validation", val_idx, 1), ("test", test_idx, 1)):
        if len(idx) < need:
            raise ValueError(f"{dataset_dir}: the {name} split has {len(idx)} converged poses; need at least {need}")
    n_act = len(ds.names)
    candidates = resolve_hidden(hidden, n_act)
    log(f"dataset {dataset_dir}: {len(ds.status)} poses, {len(ds.usable)} converged, {ds.offsets.shape[1]} "
        f"vertices, {n_act} actuators; converged train {len(train_idx)} / validation {len(val_idx)} / test "
        f"{len(test_idx)}; hidden sizes {candidates}")
    x_all = (ds.actuators - ds.lo) / (ds.hi - ds.lo)
    anchor, rest_info = _rest_anchor(ds, config)
    log(rest_info["note"])
    names, labels = regions(ds)
    edges = surface_edges(ds.base_vertices, ds.faces) if config.edge_weight > 0 else None
    results: list[TrainResult] = []
    per_hidden: dict[str, Any] = {}
    for h in candidates:
        res = train_ksnn(x_all, ds.offsets, train_idx, val_idx, h, ds.lo, ds.hi, config,
                         checkpoint=out / "checkpoints" / f"ksnn_h{h}.pt", log=log, anchor=anchor, edges=edges)
        results.append(res)
        val = surface_errors(_numpy_predict(res.weights), ds.actuators, ds.offsets, val_idx, names, labels,
                             base=ds.base_vertices, faces=ds.faces)
        per_hidden[str(h)] = {"best_epoch": res.best_epoch, "epochs_run": len(res.history["val"]),
                              "best_val_objective": res.best_val_mse, "train_seconds": round(res.seconds, 2),
                              "validation": _brief(val)}
        log(f"H={h}: best validation objective {res.best_val_mse:.4g} at epoch {res.best_epoch}; validation mean "
            f"{val['mean_euclidean_um']:.1f} µm, max {val['max_euclidean_um']:.1f} µm")
    best = min(results, key=lambda r: r.best_val_mse)
    dataset_info = {"id": ds.id, "hash": ds.content_hash(), "path": str(dataset_dir), "head": ds.head,
                    "n_poses": len(ds.status), "n_converged": len(ds.usable)}
    split_info = {"seed": ds.splits.seed, "fractions": dict(zip(SPLIT_NAMES, ds.splits.fractions, strict=True)),
                  "poses": ds.splits.sizes(),
                  "converged": {"train": len(train_idx), "validation": len(val_idx), "test": len(test_idx)}}
    training_info = {"config": asdict(config), "hidden_candidates": candidates, "selected_hidden": best.hidden,
                     "selection": SELECTION, "per_hidden": per_hidden, "rest_anchor": rest_info}
    if config.init:  # the weights it started from, by content
        training_info["init"] = {"checkpoint": config.init,
                                 "sha256": hashlib.sha256(Path(config.init).read_bytes()).hexdigest()}
    meta = predictor_metadata(
        head=ds.head, names=ds.names, units=ds.units, weights=best.weights, base_vertices=ds.base_vertices,
        faces=ds.faces, face_unit_names=ds.face_unit_names, face_unit_offsets=ds.face_unit_offsets,
        training={"dataset": dataset_info, "splits": split_info, "hidden": best.hidden},
    )
    model_path = export_predictor(out / "predictor.onnx", best.weights, meta)
    # The test split, once: the exported float32 graph, as `likeness offline evaluate` runs it.
    test = evaluate_predictor(model_path, ds, "test", config.threads)
    comparison = _compare_h_equals_a(results, best, n_act, ds, test_idx, names, labels, test)
    meta["training"] = json.dumps({"dataset": dataset_info, "splits": split_info, "hidden": best.hidden,
                                   "test": _brief(test)})
    export_predictor(model_path, best.weights, meta)
    report: dict[str, Any] = {
        "format": REPORT_FORMAT, "format_version": REPORT_VERSION, "predictor": str(model_path),
        "dataset": dataset_info, "material": material_info(ds), "mesh": mesh_info(ds), "splits": split_info,
        "training": training_info, "hidden_comparison": comparison, "test": test,
    }
    if int8:
        q_path = export_int8(model_path, out / "predictor_int8.onnx")
        report["int8"] = {"predictor": str(q_path), "test": _brief(evaluate_predictor(q_path, ds, "test",
                                                                                       config.threads))}
    _plots(out, ds, test_idx, best, results, test)
    report["seconds"] = round(time.perf_counter() - t0, 2)
    write_bytes(out / REPORT_NAME, json.dumps(report, indent=1).encode())
    log(f"test ({len(test_idx)} poses): mean {test['mean_euclidean_um']:.1f} µm, RMS "
        f"{test['rms_euclidean_um']:.1f} µm, p99 {test['p99_euclidean_um']:.1f} µm, max "
        f"{test['max_euclidean_um']:.1f} µm in {test['max_at']['region']} (H={best.hidden}) → {model_path}")
    return report


def surface_edges(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges (E, 2) of a triangle surface and their rest lengths (E,), for the edge-strain loss."""
    from offline.mesh.surface import directed_edges

    pairs = np.unique(np.sort(directed_edges(np.asarray(faces, dtype=np.int64)), axis=1), axis=0)
    length = np.linalg.norm(vertices[pairs[:, 1]] - vertices[pairs[:, 0]], axis=1)
    if len(pairs) == 0 or not np.all(length > 0):
        raise ValueError("the surface has no edges, or an edge of zero length: the edge-strain loss needs a "
                         "triangle surface without degenerate edges")
    return pairs, length


def _rest_anchor(ds: PoseDataset, config: TrainConfig) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The normalized rest pose to pin the predictor at (or None), and what the report says about it."""
    rest = ds.rest_pose
    if rest is None:
        return None, {"anchored": False, "note": "the dataset records no rest pose; the predictor is not pinned"}
    x = (rest - ds.lo) / (ds.hi - ds.lo)
    info: dict[str, Any] = {"pose": [float(v) for v in rest]}
    if not config.rest_anchor:
        return None, {**info, "anchored": False, "note": "rest anchor switched off (--no-rest-anchor)"}
    if np.any(x < 0) or np.any(x > 1):
        return None, {**info, "anchored": False, "note": "the rest pose lies outside the sampled range; not pinned"}
    return x, {**info, "anchored": True,
               "note": "predictor pinned to zero offsets at the dataset's rest pose (trained as f(x) - f(x_rest))"}


def _brief(m: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers of a metrics document (no per-region table)."""
    keys = ("n_poses", "mean_euclidean_um", "rms_euclidean_um", "p99_euclidean_um", "max_euclidean_um",
            "rmse_per_coordinate_um", "max_at", "surface_strain")
    return {k: m[k] for k in keys if k in m}


def _compare_h_equals_a(results: Sequence[TrainResult], best: TrainResult, n_act: int, ds: PoseDataset,
                        test_idx: np.ndarray, names, labels, test: dict[str, Any]) -> dict[str, Any]:
    """The paper's H = A network beside the validation-selected one, on validation (selection) and test."""
    h_a = next((r for r in results if r.hidden == n_act), None)
    if h_a is None:
        return {"note": f"H = A ({n_act}) was not among the hidden sizes trained"}
    val = {r.hidden: r.best_val_mse for r in results}
    out: dict[str, Any] = {
        "note": "selection used validation only; test figures are reported for comparison, never used to choose",
        "h_equals_a": {"hidden": n_act, "best_val_objective": val[n_act]},
        "selected": {"hidden": best.hidden, "best_val_objective": val[best.hidden], "test": _brief(test)},
    }
    if h_a is best:
        out["h_equals_a"]["test"] = _brief(test)
    else:
        out["h_equals_a"]["test"] = _brief(surface_errors(_numpy_predict(h_a.weights), ds.actuators, ds.offsets,
                                                          test_idx, names, labels, base=ds.base_vertices,
                                                          faces=ds.faces))
    return out


def _plots(out: Path, ds: PoseDataset, test_idx: np.ndarray, best: TrainResult, results: Sequence[TrainResult],
           test: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    from models.atomic import atomic_path

    pred = _numpy_predict(best.weights)(ds.actuators[test_idx])
    per_vertex = np.sqrt(((pred - np.asarray(ds.offsets[test_idx])) ** 2).sum(-1)).mean(axis=0)
    base = ds.base_vertices
    # Front view: project on the two axes of largest extent.
    axes = np.sort(np.argsort(np.ptp(base, axis=0))[::-1][:2])  # e.g. x across, y up for a face
    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    um = per_vertex * 1e6
    if len(ds.faces):
        tri = Triangulation(base[:, axes[0]], base[:, axes[1]], ds.faces)
        pc = ax.tripcolor(tri, um, shading="gouraud", cmap="viridis")
    else:
        pc = ax.scatter(base[:, axes[0]], base[:, axes[1]], c=um, s=4, cmap="viridis")
    fig.colorbar(pc, ax=ax, label="mean test vertex error (µm)")
    ax.set_aspect("equal")
    ax.set_title(f"KSNN H={best.hidden}, test: mean {test['mean_euclidean_um']:.1f} µm, "
                 f"max {test['max_euclidean_um']:.1f} µm")
    ax.set_xlabel("xyz"[axes[0]] + " (m)")
    ax.set_ylabel("xyz"[axes[1]] + " (m)")
    fig.tight_layout()
    with atomic_path(out / "vertex_error.png", suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for r in results:
        ax.semilogy(r.history["train"], label=f"train H={r.hidden}", lw=1)
        ax.semilogy(r.history["val"], "--", label=f"validation H={r.hidden}", lw=1)
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (per-axis scaled offsets)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(out / "training_curves.png", suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
