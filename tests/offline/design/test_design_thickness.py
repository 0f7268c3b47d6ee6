"""Thickness optimization on the block: adjoint gradient against finite differences, and ground-truth recovery."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from offline.design.ground_truth import BlockSettings, block_problem, run_ground_truth
from offline.design.thickness import adjoint_gradient, optimize_adjoint, sensitivities, solve_poses

SMALL = BlockSettings(size_m=(0.04, 0.02, 0.006), divisions=(8, 3, 2), n_samples=5, n_poses=2)


@pytest.mark.parametrize("order", [1, 2])
def test_adjoint_gradient_matches_finite_differences_and_sensitivities(order):
    problem, _, _ = block_problem(replace(SMALL, element_order=order), seed=3)
    assert problem.warp.mesh.order == order
    h = np.full(SMALL.n_samples, 0.006) * (1 + 0.05 * np.arange(SMALL.n_samples) / SMALL.n_samples)
    state = solve_poses(problem, h)
    g = adjoint_gradient(problem, state)
    rs, Js = sensitivities(problem, state)
    from offline.design.thickness import _reg_derivatives

    g_sens = _reg_derivatives(problem, h)[0] + sum(J.T @ r for J, r in zip(Js, rs, strict=True))
    assert np.allclose(g, g_sens, rtol=1e-8, atol=1e-12 * np.abs(g).max())
    eps = 1e-7
    for s in range(SMALL.n_samples):
        e = np.zeros_like(h)
        e[s] = eps
        fp = solve_poses(problem, h + e, state.xs).value
        fm = solve_poses(problem, h - e, state.xs).value
        assert g[s] == pytest.approx((fp - fm) / (2 * eps), rel=1e-5, abs=1e-9 * np.abs(g).max())


def test_bad_heights_are_refused():
    problem, _, _ = block_problem(SMALL, seed=0)
    with pytest.raises(ValueError, match="strictly inside"):
        optimize_adjoint(problem, np.full(SMALL.n_samples, 0.1))


@pytest.mark.parametrize("method", ["gauss-newton", "joint"])
def test_quick_ground_truth_is_recovered(method):
    report = run_ground_truth(replace(BlockSettings.quick(), method=method), seed=1)
    assert report["surface_error_before_max_m"] > 1e-4  # the uniform start is visibly wrong
    assert report["height_rel_error_max"] < 1e-3
    assert report["surface_error_max_m"] < 1e-6


@pytest.mark.slow
def test_quick_ground_truth_is_recovered_on_quadratic_tets():
    settings = replace(BlockSettings.quick(), element_order=2)
    report = run_ground_truth(settings, seed=1)
    assert report["settings"]["element_order"] == 2 and report["n_nodes"] > 2 * 117
    assert report["surface_error_before_max_m"] > 1e-4
    assert report["height_rel_error_max"] < 1e-3
    assert report["surface_error_max_m"] < 1e-6


def test_cli_ground_truth_writes_report_and_pictures(tmp_path: Path):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[3]), NUMBA_NUM_THREADS="1")
    out = tmp_path / "gt"
    proc = subprocess.run([sys.executable, "-m", "likeness", "offline", "optimize-thickness", "--ground-truth-test",
                           "--quick", "--seed", "2", "--quiet", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    report = json.loads((out / "report.json").read_text())
    assert report["seed"] == 2
    assert report["height_rel_error_max"] <= 0.01 and report["surface_error_max_m"] <= 1e-5
    assert len(report["inputs_sha256"]) == 64
    for name in report["pictures"]:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_without_ground_truth_says_what_is_missing(tmp_path: Path):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[3]), NUMBA_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-m", "likeness", "offline", "optimize-thickness", "--out",
                           str(tmp_path)], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode != 0
    assert "--ground-truth-test" in proc.stderr + proc.stdout


def test_region_weights_gradient_and_reachability_split():
    """Weighted matching: adjoint gradient = finite differences; a region node with weight 0 does not count; the
    reachability residual is at most the matching term and vanishes when the targets come from the warp itself."""
    problem, _, _ = block_problem(SMALL, seed=4)
    rng = np.random.default_rng(0)
    w = rng.uniform(0.2, 3.0, problem.region.size)
    w[:5] = 0.0
    wp = replace(problem, region_weights=w)
    h = np.full(SMALL.n_samples, 0.006) * (1 - 0.04 * np.arange(SMALL.n_samples) / SMALL.n_samples)
    state = solve_poses(wp, h)
    g = adjoint_gradient(wp, state)
    eps = 1e-7
    for s in range(SMALL.n_samples):
        e = np.zeros_like(h)
        e[s] = eps
        fd = (solve_poses(wp, h + e, state.xs).value - solve_poses(wp, h - e, state.xs).value) / (2 * eps)
        assert g[s] == pytest.approx(fd, rel=1e-5, abs=1e-9 * np.abs(g).max())
    moved = [p.target.copy() for p in problem.poses]
    for q in moved:
        q[:5] += 0.01  # far off, but with weight 0
    far = replace(wp, poses=tuple(replace(p, target=q) for p, q in zip(problem.poses, moved, strict=True)))
    assert solve_poses(far, h).match == pytest.approx(state.match, rel=1e-12)
    from offline.design.thickness import reachability_split

    rs, Js = sensitivities(wp, state)
    resid, _ = reachability_split(rs, Js)
    match = [0.5 * float(r @ r) for r in rs]
    assert sum(match) == pytest.approx(state.match, rel=1e-10)
    assert 0 <= sum(resid) < 0.05 * sum(match)  # targets made by a thickness field: nearly all reachable
    # a rigid shift of the targets is out of thickness's reach: the residual keeps most of it
    up = np.array([0.0, 0.0, 0.002])
    shifted = replace(problem, poses=tuple(replace(p, target=p.target + up) for p in problem.poses))
    st = solve_poses(shifted, h)
    rs2, Js2 = sensitivities(shifted, st)
    resid2, _ = reachability_split(rs2, Js2)
    assert sum(resid2) > 0.5 * st.match


def test_gauss_newton_stops_when_the_predicted_gain_is_spent():
    problem, _, _ = block_problem(SMALL, seed=5)
    res = optimize_adjoint(problem, np.full(SMALL.n_samples, 0.006), tol_gain=1e-3, max_iterations=30)
    assert res.converged and res.iterations < 30
    assert res.log[-1]["next_predicted_gain"] < 1e-3
    assert all("predicted_gain" in e for e in res.log[1:])
