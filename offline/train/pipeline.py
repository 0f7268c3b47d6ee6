"""Dataset → KSNN → ONNX: choose the hidden size by validation, export, measure held-out error, write the report.

Outputs in the ``out`` folder: ``predictor.onnx`` (float32), optionally ``predictor_int8.onnx``, ``report.json``
(RMSE and mean/max vertex error in µm on held-out poses, per hidden size, int8 error), ``vertex_error.png``
(mean held-out error per surface vertex) and ``training_curves.png``; ``checkpoints/`` makes training resumable.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from offline.dataset.store import PoseDataset, atomic_write_bytes
from offline.train.export import export_int8, export_predictor, predictor_metadata
from offline.train.ksnn import TrainConfig, TrainResult, hidden_candidates, split_indices, train_ksnn


def vertex_errors(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMSE per coordinate and mean/max Euclidean vertex error, all in micrometres."""
    d = np.asarray(pred, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    per_vertex = np.sqrt((d ** 2).sum(axis=-1))
    return {"rmse_um": float(np.sqrt(np.mean(d ** 2)) * 1e6), "mean_vertex_error_um": float(per_vertex.mean() * 1e6),
            "max_vertex_error_um": float(per_vertex.max() * 1e6)}


def _predict_all(model_path: Path, p: np.ndarray, threads: int, chunk: int = 256) -> np.ndarray:
    from models.predictor import SkinPredictor

    sp = SkinPredictor(model_path, threads=threads)
    return np.concatenate([sp.predict_offsets(p[s:s + chunk]) for s in range(0, len(p), chunk)])


def train_pipeline(dataset_dir: str | Path, out_dir: str | Path, config: TrainConfig | None = None,
                   hidden: Sequence[int] | None = None, int8: bool = False,
                   log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the whole training for one dataset folder; returns the report (also written to report.json)."""
    t0 = time.perf_counter()
    config = config or TrainConfig()
    ds = PoseDataset(dataset_dir)
    out = Path(out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    usable = ds.usable
    n_total = len(ds.status)
    if len(usable) < 10:
        raise ValueError(f"{dataset_dir}: only {len(usable)} converged poses; need at least 10 to train")
    x_all = (ds.actuators - ds.lo) / (ds.hi - ds.lo)
    tr_local, va_local = split_indices(len(usable), config.val_fraction, config.seed)
    train_idx, val_idx = usable[tr_local], usable[va_local]
    candidates = list(hidden) if hidden else hidden_candidates(len(ds.names))
    log(f"dataset {dataset_dir}: {n_total} poses, {len(usable)} converged, {ds.offsets.shape[1]} vertices, "
        f"{len(ds.names)} actuators; train {len(train_idx)} / held out {len(val_idx)}; hidden sizes {candidates}")
    results: list[TrainResult] = []
    for h in candidates:
        res = train_ksnn(x_all, ds.offsets, train_idx, val_idx, h, ds.lo, ds.hi, config,
                         checkpoint=out / "checkpoints" / f"ksnn_h{h}.pt", log=log)
        results.append(res)
        log(f"H={h}: best validation MSE {res.best_val_mse:.4g} (scaled) at epoch {res.best_epoch}")
    best = min(results, key=lambda r: r.best_val_mse)
    truth = np.asarray(ds.offsets[val_idx], dtype=np.float64)
    per_hidden = {}
    for r in results:
        pred = np.stack([r.weights.offsets(p) for p in ds.actuators[val_idx]])
        per_hidden[str(r.hidden)] = {**vertex_errors(pred, truth), "best_epoch": r.best_epoch,
                                     "train_seconds": round(r.seconds, 2)}
    training_info = {
        "dataset": str(Path(dataset_dir).resolve().name), "n_poses": int(n_total), "n_converged": len(usable),
        "n_train": len(train_idx), "n_held_out": len(val_idx), "hidden": best.hidden,
        "config": asdict(config),
    }
    meta = predictor_metadata(
        head=ds.head, names=ds.names, units=ds.units, weights=best.weights, base_vertices=ds.base_vertices,
        faces=ds.faces, face_unit_names=ds.face_unit_names, face_unit_offsets=ds.face_unit_offsets,
        training=training_info,
    )
    model_path = export_predictor(out / "predictor.onnx", best.weights, meta)
    pred_onnx = _predict_all(model_path, ds.actuators[val_idx], config.threads)
    held_out = vertex_errors(pred_onnx, truth)
    report: dict[str, Any] = {
        "predictor": str(model_path), "hidden": best.hidden, "held_out": held_out,
        "held_out_note": "the 20 % split, also used to pick the hidden size and the best epoch",
        "per_hidden": per_hidden, **training_info,
    }
    # Record the held-out errors inside the model too, so the runtime can show what it is running.
    meta["training"] = json.dumps({**training_info, "held_out": held_out})
    export_predictor(model_path, best.weights, meta)
    per_vertex = np.sqrt(((pred_onnx - truth) ** 2).sum(-1)).mean(axis=0)
    if int8:
        q_path = export_int8(model_path, out / "predictor_int8.onnx")
        pred_q = _predict_all(q_path, ds.actuators[val_idx], config.threads)
        report["int8"] = {"predictor": str(q_path), "held_out": vertex_errors(pred_q, truth),
                          "vs_float": vertex_errors(pred_q, pred_onnx)}
    _plots(out, ds, per_vertex, results, best.hidden, held_out)
    report["seconds"] = round(time.perf_counter() - t0, 2)
    atomic_write_bytes(out / "report.json", json.dumps(report, indent=1).encode())
    log(f"held-out: RMSE {held_out['rmse_um']:.1f} µm, mean vertex error {held_out['mean_vertex_error_um']:.1f} µm, "
        f"max {held_out['max_vertex_error_um']:.1f} µm (H={best.hidden}) → {model_path}")
    return report


def _plots(out: Path, ds: PoseDataset, per_vertex: np.ndarray, results: Sequence[TrainResult], best_hidden: int,
           held_out: dict[str, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

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
    fig.colorbar(pc, ax=ax, label="mean held-out vertex error (µm)")
    ax.set_aspect("equal")
    ax.set_title(f"KSNN H={best_hidden}: mean {held_out['mean_vertex_error_um']:.1f} µm, "
                 f"max {held_out['max_vertex_error_um']:.1f} µm")
    ax.set_xlabel("xyz"[axes[0]] + " (m)")
    ax.set_ylabel("xyz"[axes[1]] + " (m)")
    fig.tight_layout()
    fig.savefig(out / ".vertex_error.png", format="png")
    plt.close(fig)
    (out / ".vertex_error.png").replace(out / "vertex_error.png")
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for r in results:
        ax.semilogy(r.history["train"], label=f"train H={r.hidden}", lw=1)
        ax.semilogy(r.history["val"], "--", label=f"validation H={r.hidden}", lw=1)
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (per-axis scaled offsets)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / ".training_curves.png", format="png")
    plt.close(fig)
    (out / ".training_curves.png").replace(out / "training_curves.png")
