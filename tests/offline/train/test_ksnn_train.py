"""KSNN training: exported ONNX matches PyTorch, the report is real, training resumes from its checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.headspec import load_head  # noqa: E402
from models.predictor import SkinPredictor  # noqa: E402
from offline.dataset.generate import generate_dataset  # noqa: E402
from offline.dataset.sampling import sample_poses  # noqa: E402
from offline.dataset.store import PoseDataset  # noqa: E402
from offline.dataset.synthetic import SyntheticSpec  # noqa: E402
from offline.engine import SerialEngine  # noqa: E402
from offline.train.ksnn import TrainConfig, hidden_candidates, split_indices, torch_offsets, train_ksnn  # noqa: E402
from offline.train.pipeline import train_pipeline  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    head = load_head(ROOT / "heads" / "sample" / "head.toml")
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    root = tmp_path_factory.mktemp("ds")
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8)
    generate_dataset(root, spec, sample_poses(head, 150, seed=0), head=head.name, names=head.actuator_names,
                     units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(), seed=0, sampling={},
                     progress_stream=None)
    return root, head


def test_split_and_candidates():
    tr, va = split_indices(100, 0.2, seed=1)
    assert len(tr) == 80 and len(va) == 20 and not set(tr) & set(va)
    assert hidden_candidates(13) == [13, 20, 26]


def test_pipeline_exports_onnx_matching_torch_and_reports_errors(dataset, tmp_path):
    root, head = dataset
    cfg = TrainConfig(epochs=40, batch_size=32, lr=5e-3, patience=40)
    report = train_pipeline(root, tmp_path / "out", cfg, hidden=[13, 26], int8=True, log=lambda s: None)
    model = tmp_path / "out" / "predictor.onnx"
    sp = SkinPredictor(model)
    sp.check_against(head)
    assert sp.hidden == report["hidden"] and sp.hidden in (13, 26)
    ds = PoseDataset(root)
    P = ds.actuators[:20]
    ref = torch_offsets(sp.weights, P)
    np.testing.assert_allclose(sp.predict_offsets(P), ref, atol=1e-6 * max(1e-3, np.abs(ref).max()))
    np.testing.assert_allclose(sp.predict(P[0]), ref[0] + ds.base_vertices, atol=1e-6)
    held = report["held_out"]
    assert set(held) == {"rmse_um", "mean_vertex_error_um", "max_vertex_error_um"}
    # The held-out numbers are what the exported model really does on the held-out poses.
    _, va_local = split_indices(len(ds.usable), cfg.val_fraction, cfg.seed)
    va = ds.usable[va_local]
    err = np.sqrt(((sp.predict_offsets(ds.actuators[va]) - ds.offsets[va]) ** 2).sum(-1))
    assert held["mean_vertex_error_um"] == pytest.approx(err.mean() * 1e6, rel=1e-4)
    # ...and the network learned something: far better than predicting the mean pose.
    mean_pose = np.asarray(ds.offsets[ds.usable]).mean(axis=0)
    baseline = np.sqrt(((mean_pose - ds.offsets[va]) ** 2).sum(-1)).mean() * 1e6
    assert held["mean_vertex_error_um"] < 0.5 * baseline
    for name in ("report.json", "vertex_error.png", "training_curves.png"):
        assert (tmp_path / "out" / name).stat().st_size > 1000
    assert json.loads((tmp_path / "out" / "report.json").read_text())["hidden"] == report["hidden"]
    assert json.loads(sp.metadata["likeness.training"])["held_out"] == pytest.approx(held)
    # The int8 variant: MatMulNBits output layers, its measured error reported, weights readable for the Jacobian.
    q = SkinPredictor(report["int8"]["predictor"])
    q.check_against(head)
    q_err = np.sqrt(np.mean((q.predict_offsets(ds.actuators[va]) - sp.predict_offsets(ds.actuators[va])) ** 2))
    assert report["int8"]["vs_float"]["rmse_um"] == pytest.approx(q_err * 1e6, rel=1e-4)
    assert report["int8"]["vs_float"]["rmse_um"] < 0.05 * held["rmse_um"] + 1.0
    step = np.abs(sp.weights.W2).max(axis=(0, 1)) / 127  # per-column bound on the 8-bit step
    assert np.all(np.abs(q.weights.W2 - sp.weights.W2) <= step[None, None, :] + 1e-12)
    np.testing.assert_allclose(q.jacobian(P[1]), sp.jacobian(P[1]), atol=0.02 * np.abs(sp.jacobian(P[1])).max())


def test_training_resumes_from_checkpoint(dataset, tmp_path):
    root, _ = dataset
    ds = PoseDataset(root)
    x = (ds.actuators - ds.lo) / (ds.hi - ds.lo)
    tr, va = split_indices(len(ds.usable), 0.2, 0)
    ck = tmp_path / "ck.pt"
    msgs: list[str] = []
    first = train_ksnn(x, ds.offsets, ds.usable[tr], ds.usable[va], 13, ds.lo, ds.hi,
                       TrainConfig(epochs=6, patience=100), checkpoint=ck, log=msgs.append)
    assert len(first.history["val"]) == 6 and ck.exists()
    second = train_ksnn(x, ds.offsets, ds.usable[tr], ds.usable[va], 13, ds.lo, ds.hi,
                        TrainConfig(epochs=10, patience=100), checkpoint=ck, log=msgs.append)
    assert any("resumed at epoch 6" in m for m in msgs)
    assert len(second.history["val"]) == 10
    assert second.history["val"][:6] == first.history["val"]
    assert second.best_val_mse <= first.best_val_mse
