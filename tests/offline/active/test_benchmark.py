"""The benchmark harness: runs resume after an interruption, greedy beats random, fractions, the --quick report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from offline.active.benchmark import (
    BenchmarkSettings,
    ci95,
    first_reach,
    paired_differences,
    paired_final_differences,
    run_method,
    summarize,
)
from offline.active.selectors import BASELINES

ROOT = Path(__file__).resolve().parents[3]
SETTINGS = BenchmarkSettings(init=6, batch=6, budget=30, seeds=1)


class Interrupt(Exception):
    pass


def test_a_run_interrupted_between_batches_resumes_to_the_same_curve(tiny, cfg, tmp_path):
    whole = run_method("random", BASELINES["random"], tiny, 0, SETTINGS, cfg, tmp_path / "whole.json",
                       log=lambda m: None)
    calls = {"n": 0}

    def failing(ctx):
        calls["n"] += 1
        if calls["n"] == 3:
            raise Interrupt
        return BASELINES["random"](ctx)

    ck = tmp_path / "cut.json"
    with pytest.raises(Interrupt):
        run_method("random", failing, tiny, 0, SETTINGS, cfg, ck, log=lambda m: None)
    partial = json.loads(ck.read_text())
    assert not partial["complete"] and len(partial["labelled"]) == 18
    resumed = run_method("random", BASELINES["random"], tiny, 0, SETTINGS, cfg, ck, log=lambda m: None)
    assert resumed["complete"]
    assert resumed["labelled"][:18] == partial["labelled"]
    assert resumed["n_labelled"] == whole["n_labelled"] == [6, 12, 18, 24, 30]
    assert resumed["labelled"] == whole["labelled"]  # the resumed run drew what the unbroken one did
    np.testing.assert_allclose(resumed["mean_euclidean_um"], whole["mean_euclidean_um"])


def test_the_fully_informed_greedy_ends_below_random_on_a_seeded_problem(tiny, cfg, tmp_path):
    finals = {}
    for name in ("random", "greedy"):
        errs = [run_method(name, BASELINES[name], tiny, s, SETTINGS, cfg, tmp_path / f"{name}{s}.json",
                           log=lambda m: None)["mean_euclidean_um"][-1] for s in range(2)]
        finals[name] = float(np.mean(errs))
    assert finals["greedy"] < finals["random"]


def test_fraction_to_random_final_interpolates_and_reports_methods_that_never_reach_it():
    assert first_reach([10, 20, 30], [100.0, 50.0, 40.0], 75.0) == pytest.approx(15.0)
    assert first_reach([10, 20], [100.0, 90.0], 50.0) is None
    runs = {"random": [{"seed": 0, "n_labelled": [10, 20, 30], "mean_euclidean_um": [100, 60, 50], "l1_um": [1, 1, 1],
                        "select_seconds": [0, 0]}],
            "fast": [{"seed": 0, "n_labelled": [10, 20, 30], "mean_euclidean_um": [100, 50, 40], "l1_um": [1, 1, 1],
                      "select_seconds": [0, 0]}],
            "slow": [{"seed": 0, "n_labelled": [10, 20, 30], "mean_euclidean_um": [100, 90, 80], "l1_um": [1, 1, 1],
                      "select_seconds": [0, 0]}]}
    s = summarize(runs)
    assert s["random"]["fraction_to_random_final"] == pytest.approx(1.0)
    assert s["fast"]["fraction_to_random_final"] == pytest.approx(20 / 30)
    assert s["slow"]["fraction_to_random_final"] is None and s["slow"]["seeds_reaching_random_final"] == 0
    assert s["fast"]["fraction_to_random_final_ci95"] is None  # one seed: no interval


def test_intervals_over_seeds_and_paired_fraction_differences():
    assert ci95([1.0]) is None and ci95([2.0, 2.0, 2.0]) == [2.0, 2.0]
    lo, hi = ci95([1.0, 2.0, 3.0])  # mean 2, sd 1, t(0.975, 2) = 4.303
    assert lo == pytest.approx(2 - 4.303 / 3 ** 0.5, abs=1e-3) and hi == pytest.approx(2 + 4.303 / 3 ** 0.5, abs=1e-3)

    def run(seed, curve):
        return {"seed": seed, "n_labelled": [10, 20, 30], "mean_euclidean_um": curve, "l1_um": [1, 1, 1],
                "select_seconds": [0, 0]}

    runs = {"random": [run(s, [100, 60, 50 + s]) for s in range(4)],
            "fast": [run(s, [100, 45 + 2 * s, 40]) for s in range(4)]}
    s = summarize(runs)
    lo, hi = s["fast"]["fraction_to_random_final_ci95"]
    assert lo < s["fast"]["fraction_to_random_final"] < hi < 1.0
    curve = s["fast"]["curve_mean_euclidean_um"]
    assert curve["n_labelled"] == [10, 20, 30] and curve["mean"][1] == pytest.approx(48.0)
    assert curve["ci95_lo"][0] == curve["ci95_hi"][0] == 100 and curve["ci95_lo"][1] < 48.0 < curve["ci95_hi"][1]
    diff = paired_differences(s)["fast - random"]
    assert diff["seeds"] == 4 and diff["mean"] < 0 and diff["ci95"][1] < 0
    final = paired_final_differences(s)["fast - random"]  # 40 against 50..53: 11.5 µm lower on average
    assert final["seeds"] == 4 and final["mean"] == pytest.approx(-11.5) and final["ci95"][1] < 0


def test_quick_benchmark_writes_a_well_formed_report_and_resumes_from_its_checkpoints(tmp_path):
    out = tmp_path / "bench"
    cmd = [sys.executable, "-m", "likeness.cli", "offline", "al-benchmark", "--config",
           str(ROOT / "heads" / "sample" / "head.toml"), "--out", str(out), "--quick", "--seeds", "1"]
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    first = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["format"] == "likeness-al-benchmark"
    methods = ["random", "greedy", "space_filling", "committee", "lcmd", "maxdist", "genlal"]
    assert report["methods"] == methods and set(report["summary"]) == set(methods)
    for name in methods:
        (run,) = report["runs"][name]
        assert run["n_labelled"] == [6, 12, 18, 24, 30, 36]
        assert len(run["mean_euclidean_um"]) == len(run["l1_um"]) == 6
        assert all(np.isfinite(run["mean_euclidean_um"])) and all(e > 0 for e in run["l1_um"])
        assert len(set(run["labelled_pool_rows"])) == 36
    assert report["summary"]["random"]["fraction_to_random_final"] <= 1.0
    assert "oracle_fraction_to_random_final" in report and "genlal - lcmd" in report["paired_fraction_difference"]
    assert "genlal - space_filling" in report["paired_final_error_difference_um"]
    assert report["policy"]["learned"]["model"] == "features"
    hashes = report["inputs"]["hashes"]
    assert len({hashes["pool"], hashes["policy"], hashes["test"]}) == 3
    assert report["inputs"]["config_hash"].startswith("sha256:") and report["policy"]["hash"].startswith("sha256:")
    assert (out / "al_benchmark.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A second invocation finds every run and the policy checkpointed: nothing is recomputed, same report.
    second = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "loaded" in second.stderr
    again = json.loads((out / "report.json").read_text())
    assert again["runs"] == report["runs"]
    # Other policy settings in the same folder: refused by name, not answered with the policy learned before.
    third = subprocess.run([*cmd, "--validation-seeds", "2"], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=600)
    assert third.returncode != 0 and "learned with other policy settings" in third.stderr


def test_the_shipped_clustered_quadratic_pool_is_found_beside_the_config_by_what_it_holds():
    """The 4,000-pose clustered quadratic-tet pool ships as its own pack: a run asking for that pool takes it
    without ``--pool-pack``; a run asking for the same clusters on linear tets, or for other clusters, does not."""
    from offline.active.benchmark_job import BenchmarkJob, pool_pack, settings_of
    from offline.dataset.pack import read_header

    config = str(ROOT / "heads" / "sample" / "head.toml")
    shipped = ROOT / "heads" / "sample" / "al_pool_c60_quadratic.npz"
    manifest = read_header(shipped)["manifest"]
    assert manifest["n_poses"] == 4000 and manifest["sampling"]["clusters"] == 60
    assert manifest["problem"]["element_order"] == 2
    job = BenchmarkJob(config=config, out="unused", pool_poses=4000, clusters=60, element_order=2)
    assert pool_pack(job, settings_of(job)[0]) == str(shipped)
    for other in (BenchmarkJob(config=config, out="unused", pool_poses=4000, clusters=60),
                  BenchmarkJob(config=config, out="unused", pool_poses=4000, clusters=30, element_order=2)):
        assert pool_pack(other, settings_of(other)[0]) is None  # simulated


def test_a_quadratic_pool_is_simulated_not_taken_from_the_linear_shipped_pack():
    """``--element-order 2`` asks for the skin's quadratic tets: the shipped linear pack must not stand in for it."""
    from models.errors import UsageError
    from offline.active.benchmark_job import BenchmarkJob, pool_pack, settings_of

    config = str(ROOT / "heads" / "sample" / "head.toml")
    quad = BenchmarkJob(config=config, out="unused", element_order=2)
    settings = settings_of(quad)[0]
    assert settings.element_order == 2
    assert pool_pack(quad, settings) is None  # simulated
    shipped = str(ROOT / "heads" / "sample" / "al_pool.npz")
    given = BenchmarkJob(config=config, out="unused", element_order=2, pool_pack=shipped)
    with pytest.raises(UsageError, match="element_order"):
        pool_pack(given, settings_of(given)[0])
    linear = BenchmarkJob(config=config, out="unused")
    assert pool_pack(linear, settings_of(linear)[0]) == shipped
    with pytest.raises(UsageError, match="--element-order 2"):
        settings_of(BenchmarkJob(config=config, out="unused", synthetic=True, element_order=2))


def test_runs_in_worker_processes_give_the_curves_one_process_gives(tiny, cfg, tmp_path):
    """The benchmark's runs spread over two processes: every method's poses and errors as computed serially."""
    from offline.active.benchmark import run_benchmark

    settings = BenchmarkSettings(init=6, batch=6, budget=18, seeds=2)
    selectors = {name: BASELINES[name] for name in ("random", "space_filling", "greedy")}
    serial = run_benchmark(tiny, selectors, settings, cfg, tmp_path / "one", log=lambda m: None)
    lines: list[str] = []
    parallel = run_benchmark(tiny, selectors, settings, cfg, tmp_path / "two", log=lines.append, workers=2)
    assert len(lines) == 6 and all("final test error" in line for line in lines)
    for name in selectors:
        for a, b in zip(serial["runs"][name], parallel["runs"][name], strict=True):
            assert a["seed"] == b["seed"] and a["labelled"] == b["labelled"]
            np.testing.assert_allclose(a["mean_euclidean_um"], b["mean_euclidean_um"], rtol=1e-9)
    assert serial["summary"].keys() == parallel["summary"].keys()
    assert len(list((tmp_path / "two" / "runs").glob("*.json"))) == 6  # checkpoints written by the workers
