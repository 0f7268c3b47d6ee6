"""The error floor of a hidden size: exact for offsets a KSNN of that size makes, a floor under any other's RMS."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.predictor import KsnnWeights
from offline.train.capacity import floor_summary, rank_floor

ROOT = Path(__file__).resolve().parents[3]


def ksnn(seed: int, hidden: int, A: int = 5, V: int = 60) -> KsnnWeights:
    rng = np.random.default_rng(seed)
    return KsnnWeights(-np.ones(A), np.ones(A), rng.normal(size=(3, A, hidden)), rng.normal(size=(3, hidden)),
                       rng.normal(size=(3, hidden, V)) * 1e-3, rng.normal(size=(3, V)) * 1e-4)


def test_offsets_a_network_of_that_size_makes_have_no_floor_and_smaller_sizes_do():
    w = ksnn(0, hidden=4)
    P = np.random.default_rng(1).uniform(-1, 1, size=(80, 5))
    X = np.stack([w.offsets(p) for p in P])
    floors = rank_floor(X, [2, 3, 4, 6])
    assert floors[4].max() < 1e-12 and floors[6].max() < 1e-12
    assert floors[2].mean() > floors[3].mean() > 1e-7  # fewer units than made the data: an error no training removes


def test_the_rms_floor_lies_under_every_network_of_that_size():
    target = ksnn(2, hidden=8)
    P = np.random.default_rng(3).uniform(-1, 1, size=(60, 5))
    X = np.stack([target.offsets(p) for p in P])
    floor = rank_floor(X, [3])[3]
    rms_floor = np.sqrt(np.mean(floor ** 2))
    for seed in range(5):  # networks of 3 units per axis, their output layers fitted to the data in least squares
        w = ksnn(10 + seed, hidden=3)
        h = np.stack([np.tanh(w.normalize(P) @ w.W1[k] + w.b1[k]) for k in range(3)])  # (3, P, H)
        fit = np.empty_like(X)
        for k in range(3):
            design = np.hstack([h[k], np.ones((len(P), 1))])
            coef, *_ = np.linalg.lstsq(design, X[:, :, k], rcond=None)
            fit[:, :, k] = design @ coef
        assert np.sqrt(np.mean(np.sum((fit - X) ** 2, axis=-1))) >= rms_floor * (1 - 1e-9)


def test_the_summary_names_the_worst_pose_and_counts_poses_beyond_the_goal():
    dist = np.zeros((4, 10))
    dist[2, 7] = 2e-3
    dist[0, 1] = 0.5e-3
    s = floor_summary(dist, np.array([10, 11, 12, 13]), goal_max_m=1e-3)
    assert s["max_at"] == {"pose_index": 12, "vertex": 7} and s["poses_beyond_goal"] == 1
    assert s["max_euclidean_um"] == pytest.approx(2000.0)


def test_bad_offsets_and_ranks_are_refused():
    with pytest.raises(ValueError, match="offsets must be"):
        rank_floor(np.zeros((5, 3)), [1])
    with pytest.raises(ValueError, match="ranks must be positive"):
        rank_floor(np.zeros((5, 4, 3)), [0])


def test_the_command_on_the_shipped_dataset_sets_the_predictor_beside_its_floor(tmp_path):
    res = subprocess.run([sys.executable, "-m", "likeness", "offline", "capacity", "--dataset",
                          str(ROOT / "heads/sample/predictor_dataset.npz"), "--hidden", "A", "2A", "--split", "test",
                          "--predictor", str(ROOT / "heads/sample/predictor.onnx"), "--out", str(tmp_path / "f.json")],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    written = json.loads((tmp_path / "f.json").read_text())  # the printed report, with the command that made it
    assert written == out and written["command"].startswith("likeness offline capacity --dataset ")
    assert out["dataset"]["poses"] == 75 and set(out["floor"]) == {"13", "26"}
    assert out["floor"]["13"]["rms_floor_um"] > out["floor"]["26"]["rms_floor_um"] > 0
    # the shipped predictor has 26 units per axis: its RMS error on these poses is above that size's floor
    assert out["predictor"]["rms_euclidean_um"] >= out["floor"]["26"]["rms_floor_um"]
