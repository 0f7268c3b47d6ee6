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


def test_a_fit_aimed_at_the_max_trades_rms_for_a_lower_max_and_projects_poses_of_its_subspace_exactly():
    from offline.train.capacity import fit_subspaces, max_aimed_fit, project

    rng = np.random.default_rng(4)
    P, V = 200, 40
    modes = np.zeros((4, V))
    modes[0], modes[1], modes[2] = 1.0, np.linspace(-0.5, 0.5, V), 0.2 * np.cos(np.arange(V))  # broad modes (mm)...
    modes[3, 0] = 3.0  # ...and a rim vertex's own, moving in few poses: little energy, a large peak
    coef = rng.normal(size=(P, 4))
    coef[10:, 3] = 0.0
    X = np.repeat((coef @ modes)[:, :, None] * 1e-3, 3, axis=2)
    ls = rank_floor(X, [3])[3]
    fit, dist, round_ = max_aimed_fit(X, 3, rounds=30)
    assert round_ > 0 and dist.max() < 0.5 * ls.max()  # the max falls by more than half...
    assert np.sqrt(np.mean(dist ** 2)) > np.sqrt(np.mean(ls ** 2))  # ...at the cost of the RMS, which LS minimizes
    np.testing.assert_allclose(project(X, fit), dist, atol=1e-12)  # its distances are its projection's
    np.testing.assert_allclose(project(X, fit_subspaces(X, 3)), ls, atol=1e-9)  # unit weights: least squares
    inside = np.stack([fit.centres[k] + (rng.normal(size=(5, 3)) @ (fit.bases[k] / fit.vertex_weights[:, None]).T)
                       for k in range(3)], axis=2)  # poses in the fit's subspaces, never fitted on
    assert project(inside, fit).max() < 1e-12
    with pytest.raises(ValueError, match="to project on this fit"):
        project(np.zeros((2, V + 1, 3)), fit)
    with pytest.raises(ValueError, match="rounds must be positive"):
        max_aimed_fit(X, 3, rounds=0)


def test_the_command_fits_aimed_at_the_max_and_projects_other_poses(tmp_path):
    res = subprocess.run([sys.executable, "-m", "likeness", "offline", "capacity", "--dataset",
                          str(ROOT / "heads/sample/predictor_dataset.npz"), "--hidden", "A", "2A", "--split",
                          "test", "--max-aimed", "3", "--project",
                          str(ROOT / "heads/sample/predictor_dataset_ends.npz"),
                          "--predictor", str(ROOT / "heads/sample/predictor.onnx")],
                         capture_output=True, text=True, cwd=ROOT, timeout=180)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    aimed, floor = out["max_aimed"]["13"], out["floor"]["13"]
    assert out["max_aimed"]["rounds"] == 3 and aimed["max_euclidean_um"] <= floor["max_euclidean_um"]
    assert aimed["rms_floor_um"] >= floor["rms_floor_um"] * (1 - 1e-9)  # least squares has the least RMS
    proj = out["project"]
    assert proj["poses"] == 173 and set(proj["least_squares"]) == set(proj["max_aimed"]) == {"13", "26"}
    ls = proj["least_squares"]
    assert ls["13"]["rms_floor_um"] > ls["26"]["rms_floor_um"] > 0  # nested subspaces: more units, closer fit
    assert ls["13"]["strain_p99_abs"] > ls["26"]["strain_p99_abs"] > 0 and proj["predictor"]["strain_p99_abs"] > 0
    bad = subprocess.run([sys.executable, "-m", "likeness", "offline", "capacity", "--dataset",
                          str(ROOT / "heads/sample/predictor_dataset.npz"), "--max-aimed", "-1"],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert bad.returncode == 2 and "--max-aimed" in bad.stderr
