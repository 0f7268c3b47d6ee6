"""``likeness offline sweep`` on the analytic sheet: the sweep's points, its solved offsets and a predictor's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from likeness.cli import main
from models.predictor import SkinPredictor
from offline.dataset.store import PoseDataset

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[3]
HEAD = str(ROOT / "heads" / "sample" / "head.toml")


def test_a_sweep_solves_its_points_from_the_pose_and_reads_the_predictor_beside_them(tmp_path, capsys):
    from offline.train.ksnn import TrainConfig
    from offline.train.pipeline import train_pipeline

    ds_dir, pred_dir = tmp_path / "ds", tmp_path / "pred"
    assert main(["offline", "dataset", "--config", HEAD, "--synthetic", "--poses", "60", "--out", str(ds_dir),
                 "--engine", "local", "--workers", "1", "--quiet"]) == 0
    train_pipeline(ds_dir, pred_dir, TrainConfig(epochs=3, batch_size=32), hidden=["A"], log=lambda s: None)
    capsys.readouterr()
    source = PoseDataset(ds_dir)
    pose = int(source.usable[0])
    args = ["offline", "sweep", "--config", HEAD, "--synthetic", "--dataset", str(ds_dir), "--pose", str(pose),
            "--actuator", "jaw", "--to", "1.0", "--steps", "5", "--vertex", "7", "--workers", "1", "--quiet",
            "--predictor", str(pred_dir / "predictor.onnx"), "--out", str(tmp_path / "sweep")]
    assert main(args) == 0
    report = json.loads(capsys.readouterr().out)
    j = list(source.names).index("jaw")
    start = (source.actuators[pose, j] - source.lo[j]) / (source.hi[j] - source.lo[j])
    assert report["points"] == 5 and report["fraction"] == pytest.approx(np.linspace(start, 1.0, 5), abs=1e-6)
    # the first point is the dataset's pose itself: the same solved offset
    assert report["solved_mm"][0] == pytest.approx(np.asarray(source.offsets[pose][7]) * 1e3, abs=1e-3)
    sweep = PoseDataset(tmp_path / "sweep")
    pred = SkinPredictor(pred_dir / "predictor.onnx").predict_offsets(sweep.actuators[sweep.usable])[:, 7, :]
    got = report["predictors"][str(pred_dir / "predictor.onnx")]
    err = np.linalg.norm(pred - np.asarray(sweep.offsets[sweep.usable][:, 7, :]), axis=1) * 1e3
    assert got["error_mm"] == pytest.approx(err, abs=1e-3) and got["max_error_mm"] == pytest.approx(err.max(), abs=1e-3)
    steps = np.linalg.norm(np.diff(np.asarray(report["solved_mm"]), axis=0), axis=1)
    assert report["solved_largest_step_mm"] == pytest.approx(steps.max(), abs=1e-3)
    # bad input is named
    assert main([*args[:10], "no_such", *args[11:]]) == 2
    assert "no_such" in capsys.readouterr().err
    assert main([*args[:12], "1.5", *args[13:]]) == 2
    assert "--to" in capsys.readouterr().err
