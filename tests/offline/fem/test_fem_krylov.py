"""Inexact Newton: CG preconditioned by a stale factorization, and factorizations reused across solves."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from offline.fem import (
    FactorCache,
    SolverOptions,
    box_mesh,
    factorize,
    fixed,
    solve_static,
    stiffness,
)
from offline.fem.krylov import pcg
from tests.offline.fem.test_fem_solver import MAT, _indentation


def _free_block(mesh, x, bc):
    K = stiffness(mesh, MAT, x)
    free = np.setdiff1d(np.arange(3 * mesh.n_nodes), bc.dofs)
    return K[free][:, free].tocsr()


def test_pcg_with_a_stale_factor_solves_the_new_tangent() -> None:
    mesh = box_mesh((0.04, 0.04, 0.01), (8, 8, 2))
    bc = _indentation(mesh, 0.001)
    X = np.asarray(mesh.nodes)
    K0 = _free_block(mesh, X, bc)
    rng = np.random.default_rng(1)
    K1 = _free_block(mesh, X + 2e-4 * rng.standard_normal(X.shape), bc)
    b = rng.standard_normal(K1.shape[0])
    fac = factorize(K0, "superlu")
    res = pcg(K1, b, fac.solve, 1e-10, 200)
    assert res.reason == "converged" and 1 < res.iterations < 60
    assert np.linalg.norm(K1 @ res.x - b) <= 1e-10 * np.linalg.norm(b) * 1.0001
    # with its own factorization one iteration suffices
    assert pcg(K1, b, factorize(K1, "superlu").solve, 1e-10, 5).iterations == 1


def test_pcg_reports_indefinite_and_iteration_limit() -> None:
    A = sp.diags([1.0, 2.0, -3.0]).tocsr()
    res = pcg(A, np.ones(3), lambda r: r, 1e-12, 10)
    assert res.x is None and res.reason == "indefinite"
    n = 50
    B = sp.diags(np.linspace(1.0, 1e4, n)).tocsr()
    res = pcg(B, np.ones(n), lambda r: r, 1e-14, 3)
    assert res.x is None and res.reason == "max_iterations" and res.iterations == 3
    with pytest.raises(ValueError, match="rtol"):
        pcg(B, np.ones(n), lambda r: r, 0.0, 3)


@pytest.mark.parametrize("backend", ["pardiso", "superlu"])
def test_reuse_matches_exact_newton_with_fewer_factorizations(backend: str) -> None:
    from offline.fem import available_backends

    if backend not in available_backends():
        pytest.skip(f"{backend} not installed")
    mesh = box_mesh((0.04, 0.04, 0.01), (10, 10, 3))
    bc = _indentation(mesh, 0.0012)
    exact = solve_static(mesh, MAT, bc, options=SolverOptions(backend=backend, reuse_factorization=False))
    inexact = solve_static(mesh, MAT, bc, options=SolverOptions(backend=backend))
    assert exact.converged and inexact.converged
    assert exact.factorizations == exact.iterations and exact.krylov_iterations == 0
    assert inexact.factorizations == 1 < exact.factorizations
    assert inexact.krylov_iterations > 0
    assert sum(e["factorized"] for e in inexact.log) == 1 and sum(e["krylov"] for e in inexact.log) > 0
    # both meet the same residual threshold, so they agree to well below it
    assert inexact.log[-1]["residual"] <= inexact.log[-1]["tolerance"]
    u = np.abs(exact.x - np.asarray(mesh.nodes)).max()
    assert np.abs(inexact.x - exact.x).max() < 1e-5 * u
    scale = np.abs(exact.reactions).max()
    np.testing.assert_allclose(inexact.reactions, exact.reactions, rtol=0, atol=1e-5 * scale)


def test_factor_cache_carries_a_factorization_to_the_next_pose() -> None:
    mesh = box_mesh((0.04, 0.04, 0.01), (8, 8, 2))
    cache = FactorCache()
    first = solve_static(mesh, MAT, _indentation(mesh, 0.0010), options=SolverOptions(backend="superlu"),
                         cache=cache)
    assert first.factorizations == 1
    # a nearby pose with the same constrained DoFs: preconditioned by the previous solve's factorization
    second = solve_static(mesh, MAT, _indentation(mesh, 0.0011), options=SolverOptions(backend="superlu"),
                          cache=cache)
    assert second.converged and second.factorizations == 0 and second.krylov_iterations > 0
    ref = solve_static(mesh, MAT, _indentation(mesh, 0.0011),
                       options=SolverOptions(backend="superlu", reuse_factorization=False))
    assert np.abs(second.x - ref.x).max() < 1e-5 * 0.0011
    # other constrained DoFs: the cache starts afresh instead of preconditioning a different system
    third = solve_static(mesh, MAT, fixed(mesh, "z0"), options=SolverOptions(backend="superlu",
                                                                            gravity=(0, 0, -9.81)), cache=cache)
    assert third.converged and third.factorizations == 1


def test_krylov_options_are_checked() -> None:
    with pytest.raises(ValueError, match="krylov_rtol"):
        SolverOptions(krylov_rtol=0.0)
    with pytest.raises(ValueError, match="krylov_max_iterations"):
        SolverOptions(krylov_max_iterations=0)


def test_tangent_factorization_through_the_cache_preconditions_the_next_solve() -> None:
    from offline.fem import tangent_factorization

    mesh = box_mesh((0.04, 0.04, 0.01), (8, 8, 2))
    bc = _indentation(mesh, 0.0010)
    cache = FactorCache()
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu"), cache=cache)
    fac, free_idx, K = tangent_factorization(mesh, MAT, res.x, bc, backend="superlu", cache=cache)
    assert cache.factorization is fac
    g = np.random.default_rng(2).standard_normal(free_idx.size)
    lam = fac.solve(g)
    np.testing.assert_allclose(K[free_idx][:, free_idx] @ lam, g, atol=1e-8 * np.abs(g).max())
    # the next pose, warm-started from this equilibrium, where the adjoint's tangent was factored
    again = solve_static(mesh, MAT, _indentation(mesh, 0.00105), x0=res.x, options=SolverOptions(backend="superlu"),
                         cache=cache)
    assert again.converged and again.factorizations == 0
