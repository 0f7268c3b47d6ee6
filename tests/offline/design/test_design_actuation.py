"""Actuation optimization on a tiny block: gradients against finite differences, groups, ground-truth recovery."""

from __future__ import annotations

import numpy as np
import pytest

from offline.design.actuation import (
    ActuationProblem,
    ActuationSpace,
    adjoint_gradient,
    direct_gradient,
    evaluate,
    optimize_targets,
    simulate,
)
from offline.fem import SolverOptions, box_mesh, neo_hookean_from_E_nu, rigid_transform_dirichlet

SIZE = (0.04, 0.012, 0.006)


def _rot_x(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _problem(groups: bool = False) -> ActuationProblem:
    """A 40 × 12 × 6 mm bar, end x0 clamped; end x1 is a link moved by stretch, lift and twist (and, with
    ``groups``, a fourth actuator tied to the lift by a mirror group, and the lift/stretch pair coupled)."""
    mesh = box_mesh(SIZE, (8, 3, 2))
    X = np.asarray(mesh.nodes)
    axis = np.array([SIZE[0], SIZE[1] / 2, SIZE[2] / 2])

    def boundary(p: np.ndarray):
        T = np.eye(4)
        R = _rot_x(p[2])
        T[:3, :3] = R
        lift = p[1] if not groups else 0.5 * (p[1] - p[3])
        T[:3, 3] = axis - R @ axis + np.array([p[0], 0.0, lift])
        return rigid_transform_dirichlet(mesh, {"x1": T}, fixed_sets=["x0"])

    del X
    if groups:
        space = ActuationSpace(("stretch", "lift", "twist", "lift_mirror"), np.array([-0.004, -0.006, -0.4, -0.006]),
                               np.array([0.006, 0.006, 0.4, 0.006]), np.zeros(4), boundary,
                               together=(((1, 3), (1.0, -1.0)),), coupled=(((0, 1), 0.006),))
    else:
        space = ActuationSpace(("stretch", "lift", "twist"), np.array([-0.004, -0.006, -0.4]),
                               np.array([0.006, 0.006, 0.4]), np.zeros(3), boundary)
    return ActuationProblem(mesh, neo_hookean_from_E_nu(1e5, 0.45), space, np.asarray(mesh.node_sets["z1"]),
                            solver=SolverOptions(tol_force=1e-11))


def test_direct_and_adjoint_gradients_match_finite_differences():
    problem = _problem()
    target = simulate(problem, np.array([0.003, 0.002, 0.2]))[problem.region]
    z = np.array([0.001, -0.001, 0.05])
    ev = evaluate(problem, z, target)
    g_direct = direct_gradient(problem, ev, target)
    g_adj = adjoint_gradient(problem, ev, target)
    assert np.allclose(g_direct, g_adj, rtol=1e-8, atol=1e-12 * np.abs(g_adj).max())
    for i, eps in enumerate((1e-7, 1e-7, 1e-6)):
        e = np.zeros(3)
        e[i] = eps
        fd = (evaluate(problem, z + e, target, ev.x).value - evaluate(problem, z - e, target, ev.x).value) / (2 * eps)
        assert g_adj[i] == pytest.approx(fd, rel=1e-5)


def test_known_actuation_is_recovered_with_warm_start():
    problem = _problem()
    truths = [np.array([0.004, 0.003, 0.25]), np.array([-0.002, 0.004, -0.3]), np.array([0.005, -0.005, 0.1])]
    targets = [simulate(problem, p)[problem.region] for p in truths]
    results = optimize_targets(problem, targets)
    for res, p_true in zip(results, truths, strict=True):
        rng = problem.space.hi - problem.space.lo
        assert np.max(np.abs(res.p - p_true) / rng) < 1e-5
        assert np.max(np.linalg.norm(res.x[problem.region] - simulate(problem, p_true)[problem.region], axis=1)) < 1e-8
    assert results[0].start == "neutral"
    assert results[1].start in ("last target", "neutral")


def test_groups_are_respected_and_unreachable_targets_stop_at_the_limit():
    problem = _problem(groups=True)
    space = problem.space
    assert space.n_free == 3  # lift and lift_mirror are one variable
    p = space.expand(space.project(space.reduce(np.array([0.006, -0.006, 0.0, 0.006]))))
    assert space.feasible(p)
    assert p[1] == -p[3]
    assert p[0] - p[1] <= 0.006 + 1e-12
    # a target beyond the twist limit: the optimum sits at the limit, never outside it
    free = _problem()
    target = simulate(free, np.array([0.0, 0.0, 0.6]))[free.region]  # 0.6 rad > the 0.4 rad limit
    res = optimize_targets(problem, [target])[0]
    assert space.feasible(res.p)
    assert res.p[2] == pytest.approx(0.4, abs=0.02)
    assert res.match > 0


def test_bad_spaces_are_refused():
    def b(p):
        raise AssertionError

    with pytest.raises(ValueError, match="must exceed"):
        ActuationSpace(("a",), np.array([1.0]), np.array([0.0]), np.array([0.5]), b)
    with pytest.raises(ValueError, match="neutral"):
        ActuationSpace(("a",), np.array([0.0]), np.array([1.0]), np.array([2.0]), b)
    with pytest.raises(ValueError, match="max_spread"):
        ActuationSpace(("a", "b"), np.zeros(2), np.ones(2), np.zeros(2), b, coupled=(((0, 1), 0.0),))
