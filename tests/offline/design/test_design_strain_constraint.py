"""The guard's strain measure as a constraint of the actuation optimization, on a small bar: its derivatives
against finite differences, and a target beyond the strain limit whose constrained optimum lies inside it."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.strain_guard import SurfaceStrain
from offline.design.actuation import adjoint_gradient, direct_gradient, evaluate, optimize_targets, simulate
from offline.design.strain_constraint import StrainConstraint, strain_jacobian
from offline.fem import boundary_faces

sys.path.insert(0, str(Path(__file__).parent))
from test_design_actuation import _problem


def _top_surface(problem) -> tuple[np.ndarray, SurfaceStrain]:
    """The bar's top face (node set z1) as the guard's measured surface (8 mm neighbourhoods, no rim band)."""
    mesh = problem.mesh
    top = np.asarray(mesh.node_sets["z1"])
    bf = boundary_faces(mesh)
    member = np.zeros(mesh.n_nodes, dtype=bool)
    member[top] = True
    lookup = np.full(mesh.n_nodes, -1)
    lookup[top] = np.arange(top.size)
    faces = lookup[bf[member[bf].all(axis=1)]]
    return top, SurfaceStrain(np.asarray(mesh.nodes)[top], faces, None, radius=0.008, band=0.0)


def test_principal_strain_derivatives_match_finite_differences():
    _, surf = _top_surface(_problem())
    rng = np.random.default_rng(1)
    pos = surf.rest + 1e-3 * rng.standard_normal(surf.rest.shape)
    eps, deps = strain_jacobian(surf, pos)
    assert np.allclose(eps, surf.triangle_strains(pos))
    h = 1e-7
    for t in range(0, len(surf.faces), 7):
        for v in range(3):
            for c in range(3):
                plus, minus = pos.copy(), pos.copy()
                plus[surf.faces[t, v], c] += h
                minus[surf.faces[t, v], c] -= h
                fd = (surf.triangle_strains(plus)[t] - surf.triangle_strains(minus)[t]) / (2 * h)
                assert fd == pytest.approx(deps[t, :, v, c], rel=1e-5, abs=1e-6 * np.abs(deps[t]).max())


def test_constrained_objective_gradient_matches_finite_differences():
    problem = _problem()
    top, surf = _top_surface(problem)
    con = StrainConstraint(surf, top, -0.2, 0.06, margin=0.005, weight=100.0)
    cp = replace(problem, strain=con)
    target = simulate(problem, np.array([0.005, 0.002, 0.1]))[problem.region]
    z = np.array([0.004, 0.001, 0.05])
    ev = evaluate(cp, z, target)
    assert ev.strain[1] > con.strain_max and ev.strain_penalty > 0  # the penalty is active here
    assert ev.strain == pytest.approx(surf.extremes(ev.x[top]))
    g_direct, g_adj = direct_gradient(cp, ev, target), adjoint_gradient(cp, ev, target)
    assert np.allclose(g_direct, g_adj, rtol=1e-8, atol=1e-12 * np.abs(g_adj).max())
    assert not np.allclose(g_adj, direct_gradient(problem, evaluate(problem, z, target), target), rtol=1e-3)
    for i, step in enumerate((1e-7, 1e-7, 1e-6)):
        e = np.zeros(3)
        e[i] = step
        fd = (evaluate(cp, z + e, target, ev.x).value - evaluate(cp, z - e, target, ev.x).value) / (2 * step)
        assert g_adj[i] == pytest.approx(fd, rel=1e-5)
    # with augmented-Lagrangian multipliers (shifted hinges) at another weight
    lam = con.multipliers(ev.x, 300.0)
    ev2 = evaluate(cp, z, target, strain_weight=300.0, strain_lam=lam)
    g2 = adjoint_gradient(cp, ev2, target)
    assert np.allclose(direct_gradient(cp, ev2, target), g2, rtol=1e-8, atol=1e-12 * np.abs(g2).max())
    for i, step in enumerate((1e-7, 1e-7, 1e-6)):
        e = np.zeros(3)
        e[i] = step
        fd = (evaluate(cp, z + e, target, ev.x, 300.0, lam).value
              - evaluate(cp, z - e, target, ev.x, 300.0, lam).value) / (2 * step)
        assert g2[i] == pytest.approx(fd, rel=1e-5)


def test_target_beyond_the_strain_limit_is_matched_inside_it():
    problem = _problem()
    top, surf = _top_surface(problem)
    con = StrainConstraint(surf, top, -0.2, 0.06, margin=0.005, weight=100.0)
    target = simulate(problem, np.array([0.005, 0.002, 0.1]))[problem.region]
    free = optimize_targets(problem, [target])[0]
    assert surf.extremes(free.x[top])[1] > 0.12  # unconstrained: the target itself, far beyond +6 %
    res = optimize_targets(replace(problem, strain=con), [target])[0]
    lo, hi = surf.extremes(res.x[top])  # the guard's own measure, exact
    assert res.strain_inside and con.strain_min <= lo and hi <= con.strain_max
    assert hi > con.strain_max - 0.02  # pressed against the limit, not pulled back further than needed
    assert problem.space.feasible(res.p)
    # better than the guard's remedy: the unconstrained optimum pulled back toward neutral until its strain is no
    # more than the constrained optimum's
    lo_t, hi_t = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo_t + hi_t)
        if surf.extremes(simulate(problem, mid * free.p)[top])[1] <= hi:
            lo_t = mid
        else:
            hi_t = mid
    pulled = simulate(problem, lo_t * free.p)[problem.region]
    assert np.sum((res.x[problem.region] - target) ** 2) < 0.99 * np.sum((pulled - target) ** 2)


def test_bad_constraints_are_refused():
    problem = _problem()
    top, surf = _top_surface(problem)
    with pytest.raises(ValueError, match="strain_min"):
        StrainConstraint(surf, top, 0.1, 0.5)
    with pytest.raises(ValueError, match="nodes"):
        StrainConstraint(surf, top[:-1], -0.2, 0.5)
    with pytest.raises(ValueError, match="margin"):
        StrainConstraint(surf, top, -0.2, 0.5, margin=0.3)
