"""Pose datasets: sampling rules, warm-started generation, crash and kill recovery, non-converged poses, Dask."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from offline.dataset.generate import generate_dataset
from offline.dataset.sampling import sample_poses
from offline.dataset.store import STATUS_CONVERGED, STATUS_NOT_CONVERGED, PoseDataset, PoseStore
from offline.dataset.synthetic import SyntheticSpec
from offline.engine import DaskEngine, LocalPoolEngine, SerialEngine

ROOT = Path(__file__).resolve().parents[3]
HEAD_PATH = ROOT / "heads" / "sample" / "head.toml"


@pytest.fixture(scope="module")
def head():
    return load_head(HEAD_PATH)


def ranges(head):
    return np.array([a.min for a in head.actuators]), np.array([a.max for a in head.actuators])


def run(head, root, spec, samples, engine, **kw):
    lo, hi = ranges(head)
    return generate_dataset(root, spec, samples, head=head.name, names=head.actuator_names, units=["rad"] * len(lo),
                            lo=lo, hi=hi, engine=engine, seed=0, sampling={"boundary_prob": 0.25},
                            progress_stream=None, **kw)


def test_sampling_honours_ranges_groups_and_seed(head):
    P = sample_poses(head, 400, seed=3, boundary_prob=0.3)
    lo, hi = ranges(head)
    assert P.shape == (400, len(lo))
    assert np.all(lo - 1e-12 <= P) and np.all(hi + 1e-12 >= P)
    assert len(np.unique(np.round(P, 9), axis=0)) == 400
    idx = {n: i for i, n in enumerate(head.actuator_names)}
    for g in head.groups:
        cols = P[:, [idx[n] for n in g.actuators]]
        if g.kind == "together":
            assert np.all(cols == cols[:, :1])
        if g.kind == "coupled":
            assert np.all(np.ptp(cols, axis=1) <= g.max_spread + 1e-12)
    # boundary values appear (about 30 % of free actuators), interior values too
    jaw = P[:, idx["jaw"]]
    at_bound = np.isclose(jaw, lo[idx["jaw"]]) | np.isclose(jaw, hi[idx["jaw"]])
    assert 0.15 < at_bound.mean() < 0.45
    np.testing.assert_array_equal(P, sample_poses(head, 400, seed=3, boundary_prob=0.3))
    assert not np.array_equal(P, sample_poses(head, 400, seed=4, boundary_prob=0.3))
    with pytest.raises(ValueError, match="distinct"):
        sample_poses(head, 5000, seed=0, boundary_prob=1.0, max_rounds=3)


def test_generation_warm_starts_records_nonconverged_and_reads_memory_mapped(tmp_path, head):
    lo, hi = ranges(head)
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8, nonconverged_if_sum_above=9.0)
    samples = sample_poses(head, 40, seed=1)
    summary = run(head, tmp_path / "ds", spec, samples, SerialEngine())
    assert summary["complete"] and summary["done"] == 40 and summary["failed"] == 0
    ds = PoseDataset(tmp_path / "ds")
    assert isinstance(ds.offsets, np.memmap)
    x = (samples - lo) / (hi - lo)
    expected_nc = x.sum(axis=1) > 9.0
    assert expected_nc.any()
    np.testing.assert_array_equal(ds.status == STATUS_NOT_CONVERGED, expected_nc)
    assert set(ds.usable) == set(np.flatnonzero(ds.status == STATUS_CONVERGED))
    # Stored surfaces are the problem's solutions.
    prob = spec.build()
    for i in (0, 17, 39):
        ref = prob.solve(samples[i], None).surface
        np.testing.assert_allclose(ds.offsets[i] + ds.base_vertices, ref, atol=1e-6)
    # Warm starts from the nearest solved pose cut Newton iterations compared with a cold start.
    store = PoseStore(tmp_path / "ds")
    warm_iters = [store.read_pose(i).iterations for i in range(10, 40)]
    cold_iters = [prob.solve(samples[i], None).iterations for i in range(10, 40)]
    assert np.mean(warm_iters) < np.mean(cold_iters)


def test_worker_crash_during_generation_loses_no_pose(tmp_path, head):
    lo, hi = ranges(head)
    marks = tmp_path / "marks"
    marks.mkdir()
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=6, crash_marker_dir=str(marks), crash_indices=(4, 11))
    samples = sample_poses(head, 16, seed=2)
    with LocalPoolEngine(2) as eng:
        summary = run(head, tmp_path / "ds", spec, samples, eng)
        assert eng.rebuilds >= 1
    assert (marks / "crashed_4").exists() and (marks / "crashed_11").exists()
    assert summary["complete"] and summary["failed"] == 0
    assert PoseStore(tmp_path / "ds").done() == set(range(16))


def test_killed_cli_run_resumes_without_redoing_poses(tmp_path):
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "likeness", "offline", "dataset", "--config", str(HEAD_PATH), "--synthetic",
           "--poses", "400", "--out", str(out), "--engine", "serial", "--seed", "5"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    store = PoseStore(out)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(store.done()) < 20:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    first = store.done()
    assert 20 <= len(first) < 400, "the run should have been killed part-way"
    stamps = {i: store.pose_path(i).stat().st_mtime_ns for i in first}
    res = subprocess.run([*cmd, "--quiet"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["complete"] and summary["done"] == 400
    assert summary["solved_now"] == 400 - len(first)
    assert all(store.pose_path(i).stat().st_mtime_ns == t for i, t in stamps.items())
    ds = PoseDataset(out)
    assert ds.offsets.shape[0] == 400 and np.all(np.isfinite(ds.offsets))
    # A different sampling into the same folder is refused, naming the key.
    bad = subprocess.run([*cmd[:-1], "6"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "seed" in bad.stderr


def test_dask_local_generation_matches_serial(tmp_path, head):
    pytest.importorskip("dask.distributed")
    lo, hi = ranges(head)
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=6)
    samples = sample_poses(head, 12, seed=7)
    run(head, tmp_path / "serial", spec, samples, SerialEngine())
    with DaskEngine(None, n_workers=2) as eng:
        summary = run(head, tmp_path / "dask", spec, samples, eng)
    assert summary["complete"]
    a, b = PoseDataset(tmp_path / "serial"), PoseDataset(tmp_path / "dask")
    np.testing.assert_allclose(np.asarray(a.offsets), np.asarray(b.offsets), atol=1e-9)


def test_resume_removes_temp_files_of_a_killed_run(tmp_path, head):
    lo, hi = ranges(head)
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=6)
    samples = sample_poses(head, 6, seed=4)
    root = tmp_path / "ds"
    run(head, root, spec, samples, SerialEngine(), max_poses=3)
    store = PoseStore(root)
    leftovers = [store.poses_dir / ".pose_000004.npz.k2j3h4.tmp", root / ".offsets.npy.tmp",
                 root / ".failures.json.x8a9.tmp"]
    for f in leftovers:
        f.write_bytes(b"half a file")
    keep = root / "notes.tmp"  # not a hidden temp file of ours
    keep.write_text("operator notes")
    summary = run(head, root, spec, samples, SerialEngine())
    assert summary["complete"] and summary["solved_now"] == 3
    assert not [f for f in leftovers if f.exists()] and keep.exists()


def test_a_dataset_takes_over_the_poses_an_earlier_one_of_the_same_problem_solved(tmp_path, head):
    """``reuse``: planned poses another dataset of the same physics solved and converged are copied (surface and
    all, under the new index), the rest solved; not-converged ones are solved again; other physics is refused."""
    from models.errors import SpecError

    lo, hi = ranges(head)
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=6, nonconverged_if_sum_above=8.0)
    first = sample_poses(head, 20, seed=4)
    run(head, tmp_path / "a", spec, first, SerialEngine())
    a = PoseDataset(tmp_path / "a")
    fresh = sample_poses(head, 6, seed=5)
    second = np.concatenate([fresh[:3], first[4:16], fresh[3:]])  # 12 known poses among 6 new ones
    summary = run(head, tmp_path / "b", spec, second, SerialEngine(), reuse=tmp_path / "a")
    known_converged = a.status[4:16] == STATUS_CONVERGED
    assert 0 < known_converged.sum() < 12  # some known poses did not converge: they are solved again
    assert summary["complete"] and summary["reused"] == int(known_converged.sum())
    assert summary["solved_now"] == len(second) - summary["reused"]
    b = PoseDataset(tmp_path / "b")
    np.testing.assert_array_equal(b.actuators, second)
    np.testing.assert_array_equal(b.offsets[3:15][known_converged], a.offsets[4:16][known_converged])
    store = PoseStore(tmp_path / "b")
    assert [store.read_pose(i).index for i in range(len(second))] == list(range(len(second)))
    prob = spec.build()
    for i in (0, 8, 17):
        np.testing.assert_allclose(b.offsets[i] + b.base_vertices, prob.solve(second[i], None).surface, atol=1e-6)
    other = SyntheticSpec(tuple(lo), tuple(hi), grid=6, amplitude=0.005)
    with pytest.raises(SpecError, match="problem"):
        run(head, tmp_path / "c", other, second, SerialEngine(), reuse=tmp_path / "a")
    from offline.dataset.pack import pack_dataset, unpack_dataset

    pack_dataset(tmp_path / "a", tmp_path / "a.npz")
    unpack_dataset(tmp_path / "a.npz", tmp_path / "a-unpacked")
    with pytest.raises(SpecError, match="no pose files"):  # an unpacked pack has no solver states to take over
        run(head, tmp_path / "d", spec, second, SerialEngine(), reuse=tmp_path / "a-unpacked")
