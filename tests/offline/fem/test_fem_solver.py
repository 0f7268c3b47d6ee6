"""Newton solver behaviour: quadratic convergence, large compression with load steps, failures, backends, BCs."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from offline.fem import (
    Dirichlet,
    NotConverged,
    SolverOptions,
    available_backends,
    box_mesh,
    combine,
    cylinder_mesh,
    element_min_jacobian,
    factorize,
    fixed,
    internal_forces,
    make_solver,
    neo_hookean,
    rigid_transform_dirichlet,
    solve_static,
    stiffness,
)

MAT = neo_hookean(3.0e4, 3.0e5)


def _indentation(mesh, depth: float) -> Dirichlet:
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    c = X[top].mean(axis=0)
    half = 0.26 * (X.max(axis=0) - X.min(axis=0))
    patch = top[np.all(np.abs(X[top, :2] - c[:2]) <= half[:2], axis=1)]
    return combine(Dirichlet(patch, X[patch] + [0.0, 0.0, -depth]), fixed(mesh, "z0"))


def test_newton_converges_quadratically() -> None:
    mesh = box_mesh((0.04, 0.04, 0.01), (8, 8, 2))
    # exact Newton (a new factorization per iteration); the inexact variant is tested in test_fem_krylov
    res = solve_static(mesh, MAT, _indentation(mesh, 0.0015),
                       options=SolverOptions(backend="superlu", tol_force=1e-12, reuse_factorization=False))
    assert res.converged and res.load_steps == 1
    r = np.array([e["residual"] for e in res.log])
    assert all(e["alpha"] == 1.0 for e in res.log[:-1])
    assert all(e["projected"] == 0 for e in res.log)
    # once in the basin: r_{k+1} <= C r_k^2 (quadratic), i.e. the exponent log r_{k+1} / log r_k approaches 2
    scale = r[1]
    rel = r[1:] / scale
    tail = rel[rel < 1e-2]
    assert len(tail) >= 2
    for a, b in itertools.pairwise(tail):
        if b > 1e-14:
            assert np.log(b) / np.log(a) > 1.7
    assert len(r) <= 7


def test_large_compression_converges_with_load_steps() -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    bc = combine(Dirichlet(top, X[top] + [0.0, 0.0, -0.004]), fixed(mesh, "z0"))  # 40 % compression
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu", load_steps=4))
    assert res.converged and res.load_steps == 4
    assert element_min_jacobian(mesh, res.x).min() > 0
    assert np.allclose(res.x[top, 2], 0.006)
    total = res.reaction_total()
    assert abs(total[2]) < 1e-9 * np.abs(res.reactions).max()  # top and bottom reactions balance
    on_top = np.isin(bc.nodes, top)
    assert res.reactions[on_top, 2].sum() < 0  # the constraint pushes the top down
    free = np.setdiff1d(np.arange(mesh.n_nodes), bc.nodes)
    assert np.abs(internal_forces(mesh, MAT, res.x)[free]).max() <= 1e-6 * max(1.0, np.abs(res.reactions).max())


def test_auto_load_steps_and_halving_reach_large_compression() -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    bc = combine(Dirichlet(top, X[top] + [0.002, 0.0, -0.0045]), fixed(mesh, "z0"))
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu", load_steps="auto"))
    assert res.converged and res.load_steps >= 2
    assert element_min_jacobian(mesh, res.x).min() > 0


def test_not_converged_raises_with_saved_state(tmp_path) -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (2, 2, 2))
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    bc = combine(Dirichlet(top, X[top] + [0.0, 0.0, -0.003]), fixed(mesh, "z0"))
    opts = SolverOptions(backend="superlu", max_iterations=1, max_load_step_halvings=1, failure_dir=tmp_path)
    with pytest.raises(NotConverged) as info:
        solve_static(mesh, MAT, bc, options=opts)
    err = info.value
    assert not err.result.converged
    assert err.state_path is not None and err.state_path.parent == tmp_path and err.state_path.exists()
    with np.load(err.state_path) as z:
        assert z["x"].shape == (mesh.n_nodes, 3)
        assert np.array_equal(z["dirichlet_nodes"], bc.nodes)
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"]


def test_backends_agree() -> None:
    backends = available_backends()
    assert "superlu" in backends
    mesh = box_mesh((0.03, 0.03, 0.01), (6, 6, 2))
    bc = _indentation(mesh, 0.001)
    results = {b: solve_static(mesh, MAT, bc, options=SolverOptions(backend=b, tol_force=1e-10)) for b in backends}
    ref = results["superlu"]
    for b, r in results.items():
        assert r.converged, b
        assert np.abs(r.x - ref.x).max() < 1e-10, b
        assert np.allclose(r.reaction_total(), ref.reaction_total(), atol=1e-9)


@pytest.mark.parametrize("backend", available_backends())
def test_factorization_is_reusable_and_detects_indefinite(backend: str) -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (2, 2, 2))
    K = stiffness(mesh, MAT, np.asarray(mesh.nodes))
    free = np.setdiff1d(np.arange(K.shape[0]), 3 * mesh.node_sets["z0"][:, None] + np.arange(3))
    Kff = K[free][:, free].tocsr()
    fac = factorize(Kff, backend)
    rng = np.random.default_rng(0)
    B = rng.standard_normal((Kff.shape[0], 2))
    for b in (B[:, 0], B[:, 1]):
        assert np.allclose(Kff @ fac.solve(b), b, rtol=1e-8, atol=1e-8 * np.abs(b).max())
    if backend != "superlu":
        from offline.fem import NotPositiveDefinite

        solver = make_solver(backend)
        with pytest.raises(NotPositiveDefinite):
            solver.factor(-Kff)
        # the same solver recovers: a positive definite matrix of the same pattern factors fine afterwards
        fac2 = solver.factor(Kff)
        assert np.allclose(Kff @ fac2.solve(B[:, 0]), B[:, 0], rtol=1e-8, atol=1e-8 * np.abs(B).max())


def test_rigid_transform_dirichlet_twists_a_cylinder() -> None:
    mesh = cylinder_mesh(0.01, 0.02, 3, 4)
    X = np.asarray(mesh.nodes)
    th = np.deg2rad(30.0)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    T[2, 3] = -0.002
    bc = rigid_transform_dirichlet(mesh, {"top": T}, fixed_sets=["bottom"])
    top, bottom = mesh.node_sets["top"], mesh.node_sets["bottom"]
    assert np.allclose(bc.positions[np.isin(bc.nodes, top)], X[top] @ T[:3, :3].T + T[:3, 3])
    assert np.allclose(bc.positions[np.isin(bc.nodes, bottom)], X[bottom])
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu"))
    assert res.converged
    on_top = np.isin(bc.nodes, top)
    torque = np.cross(res.x[bc.nodes[on_top]], res.reactions[on_top])[:, 2].sum()
    assert torque > 0  # the constraint twists the top the way it was turned
    # first set in the mapping wins for shared nodes
    both = mesh.with_node_sets(a=top[:5], b=top[:3])
    d = rigid_transform_dirichlet(both, {"a": T, "b": np.eye(4)})
    assert np.allclose(d.positions[np.isin(d.nodes, top[:3])], X[top[:3]] @ T[:3, :3].T + T[:3, 3])
    with pytest.raises(KeyError, match="no node set 'nope'"):
        rigid_transform_dirichlet(mesh, {"nope": T})


def test_gravity_sag_reaction_balances_weight() -> None:
    mesh = box_mesh((0.04, 0.01, 0.01), (8, 2, 2))
    g = (0.0, 0.0, -9.81)
    res = solve_static(mesh, MAT, fixed(mesh, "x0"), options=SolverOptions(backend="superlu", gravity=g))
    assert res.converged
    weight = MAT.density * 0.04 * 0.01 * 0.01 * 9.81
    assert res.reaction_total() == pytest.approx([0.0, 0.0, weight], rel=1e-6, abs=1e-9)
    assert res.x[mesh.node_sets["x1"], 2].mean() < np.asarray(mesh.nodes)[mesh.node_sets["x1"], 2].mean()


def test_bad_inputs_have_clear_errors() -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    with pytest.raises(ValueError, match="backend"):
        solve_static(mesh, MAT, fixed(mesh, "z0"), options=SolverOptions(backend="mumps"))
    with pytest.raises(ValueError, match="load_steps"):
        SolverOptions(load_steps=0)
    with pytest.raises(ValueError, match="duplicate"):
        Dirichlet([1, 1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="out of range"):
        solve_static(mesh, MAT, Dirichlet([100], np.zeros((1, 3))))
    with pytest.raises(ValueError, match="rigid motions"):
        solve_static(mesh, MAT, Dirichlet([0], np.zeros((1, 3))))
    shear = np.eye(4)
    shear[0, 1] = 0.2
    with pytest.raises(ValueError, match="node set 'z1' is not a rigid motion"):
        rigid_transform_dirichlet(mesh, {"z1": shear})


@pytest.mark.parametrize("backend", [b for b in available_backends() if b != "superlu"])
def test_psd_projection_is_used_only_as_fallback_and_converges(backend: str) -> None:
    """Cholesky backends report the indefinite tangent of a 60 % one-step compression; projection rescues it."""
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    bc = combine(Dirichlet(top, X[top] + [0.0, 0.0, -0.006]), fixed(mesh, "z0"))  # 60 % in one step
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend=backend, load_steps=1))
    assert res.converged
    projected = [e["projected"] for e in res.log]
    assert any(projected)  # needed on the way ...
    assert projected[-2] == 0  # ... but not near the solution, where the Hessian is positive definite
    assert element_min_jacobian(mesh, res.x).min() > 0


def test_warm_start_from_a_solution_needs_no_iteration() -> None:
    mesh = box_mesh((0.02, 0.02, 0.01), (4, 4, 2))
    bc = _indentation(mesh, 0.001)
    first = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu"))
    again = solve_static(mesh, MAT, bc, x0=first.x, options=SolverOptions(backend="superlu"))
    assert again.converged and again.iterations == 0
    assert np.array_equal(again.x, first.x)
    with pytest.raises(ValueError, match="x0 must have shape"):
        solve_static(mesh, MAT, bc, x0=first.x[:-1])


def test_tangent_factorization_gives_boundary_sensitivities() -> None:
    """δu_f = −K_ff⁻¹ K_fc δc at equilibrium matches finite differences of full nonlinear solves."""
    from offline.fem import tangent_factorization

    mesh = box_mesh((0.02, 0.02, 0.01), (4, 4, 2))
    bc = _indentation(mesh, 0.001)
    opts = SolverOptions(backend="superlu", tol_force=1e-12)
    base = solve_static(mesh, MAT, bc, options=opts)
    fac, free, K = tangent_factorization(mesh, MAT, base.x, bc)
    on_patch = bc.positions[:, 2] < np.asarray(mesh.nodes)[bc.nodes, 2]
    dc = np.zeros(3 * mesh.n_nodes)
    dc[3 * bc.nodes[on_patch] + 2] = 1.0  # move the indenter along +z (slightly less indentation)
    du_f = -fac.solve((K @ dc)[free])
    h = 1e-6
    pos = np.array(bc.positions)
    pos[on_patch, 2] += h
    plus = solve_static(mesh, MAT, Dirichlet(bc.nodes, pos), x0=base.x, options=opts)
    fd = (plus.x.ravel() - base.x.ravel())[free] / h
    assert np.linalg.norm(fd - du_f) <= 1e-4 * np.linalg.norm(du_f)


def test_boundary_lands_exactly_and_energy_decreases_once_it_is_in_place() -> None:
    """A large shear + compression: each load step puts the constrained nodes on its target in its first iteration,
    after which Newton on the free DoFs never increases the energy; the final boundary equals the targets bit for
    bit (no round-off from interpolating the load factor)."""
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    X = np.asarray(mesh.nodes)
    top = mesh.node_sets["z1"]
    bc = combine(Dirichlet(top, X[top] + [0.0031, 0.0007, -0.0033]), fixed(mesh, "z0"))
    res = solve_static(mesh, MAT, bc, options=SolverOptions(backend="superlu", load_steps=3))
    assert res.converged
    assert np.array_equal(res.x[bc.nodes], bc.positions)
    by_step: dict[int, list[float]] = {}
    for row in res.log:
        by_step.setdefault(row["step"], []).append(row["energy"])
    assert len(by_step) == 3
    for energies in by_step.values():
        after = np.asarray(energies[1:])  # from the second iteration on the boundary is in place
        assert after.size >= 1
        assert np.all(np.diff(after) <= 1e-12 * np.abs(after).max())
