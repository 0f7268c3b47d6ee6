"""Physical consistency: patch test, rigid-motion invariance, uniaxial stretch vs closed form, gravity loads."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem import (
    Dirichlet,
    SolverOptions,
    box_mesh,
    combine,
    gravity_forces,
    internal_forces,
    mooney_rivlin,
    neo_hookean,
    nodal_masses,
    solve_static,
    total_energy,
    uniaxial_neo_hookean,
    yeoh,
)
from offline.fem.closed_form import uniaxial

MAT = neo_hookean(3.0e4, 3.0e5)


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("order", [1, 2])
def test_patch_test_affine_boundary_is_reproduced_inside(order: int) -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 3, 3), order=order)
    X = np.asarray(mesh.nodes)
    A = np.array([[1.2, 0.1, 0.0], [0.05, 0.9, 0.1], [0.0, -0.1, 1.1]])
    b = np.array([0.001, -0.002, 0.0005])
    boundary = np.unique(np.concatenate([mesh.node_sets[k] for k in ("x0", "x1", "y0", "y1", "z0", "z1")]))
    interior = np.setdiff1d(np.arange(mesh.n_nodes), boundary)
    assert interior.size > 0
    res = solve_static(mesh, MAT, Dirichlet(boundary, X[boundary] @ A.T + b),
                       options=SolverOptions(backend="superlu", tol_force=1e-10))
    assert res.converged
    exact = X @ A.T + b
    assert np.abs(res.x[interior] - exact[interior]).max() < 1e-10 * 0.01


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("mat", [MAT, mooney_rivlin(1e4, 3e3, 2e5), yeoh(1e4, -500.0, 100.0, 2e5)],
                         ids=["nh", "mr", "yeoh"])
def test_rigid_motion_gives_zero_force_and_invariant_energy(order: int, mat) -> None:
    mesh = box_mesh((0.02, 0.01, 0.01), (2, 1, 1), order=order)
    X = np.asarray(mesh.nodes)
    R, t = _rotation(5), np.array([0.3, -0.2, 0.1])
    assert total_energy(mesh, mat, X @ R.T + t) == pytest.approx(0.0, abs=1e-12)
    assert np.abs(internal_forces(mesh, mat, X @ R.T + t)).max() < 1e-9
    rng = np.random.default_rng(2)
    x = X + 0.001 * rng.standard_normal(X.shape)
    f = internal_forces(mesh, mat, x)
    assert total_energy(mesh, mat, x @ R.T + t) == pytest.approx(total_energy(mesh, mat, x), rel=1e-10)
    assert np.allclose(internal_forces(mesh, mat, x @ R.T + t), f @ R.T, atol=1e-10 * np.abs(f).max())


def _uniaxial_box(mesh, stretch: float) -> Dirichlet:
    """Frictionless ends: normal displacement only on x0 / x1, plus three point conditions removing rigid modes."""
    X = np.asarray(mesh.nodes)
    lx = X[:, 0].max()
    x0, x1 = mesh.node_sets["x0"], mesh.node_sets["x1"]
    only_x = np.zeros((1, 3), bool)
    only_x[0, 0] = True
    ends = combine(
        Dirichlet(x0, X[x0], np.repeat(only_x, len(x0), 0)),
        Dirichlet(x1, X[x1] + [(stretch - 1) * lx, 0, 0], np.repeat(only_x, len(x1), 0)),
    )
    corner = int(np.flatnonzero(np.all(X == 0, axis=1))[0])
    ey = int(np.flatnonzero((X[:, 0] == 0) & (X[:, 2] == 0) & (X[:, 1] == X[:, 1].max()))[0])
    ez = int(np.flatnonzero((X[:, 0] == 0) & (X[:, 1] == 0) & (X[:, 2] == X[:, 2].max()))[0])
    pins = Dirichlet([corner, ey, ez], X[[corner, ey, ez]],
                     np.array([[True, True, True], [True, False, True], [True, True, False]]))
    return combine(pins, ends)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("stretch", [1.4, 0.75])
def test_uniaxial_stretch_matches_closed_form(order: int, stretch: float) -> None:
    mu, kappa = 3.0e4, 1.5e5
    mesh = box_mesh((0.02, 0.01, 0.01), (4, 2, 2), order=order)
    bc = _uniaxial_box(mesh, stretch)
    res = solve_static(mesh, neo_hookean(mu, kappa), bc,
                       options=SolverOptions(backend="superlu", tol_force=1e-9, load_steps=2))
    assert res.converged
    on_x1 = np.isin(bc.nodes, mesh.node_sets["x1"])
    force = res.reactions[on_x1, 0].sum()
    p11, lat = uniaxial_neo_hookean(mu, kappa, stretch)
    assert force == pytest.approx(p11 * 0.01 * 0.01, rel=5e-3)
    assert force == pytest.approx(p11 * 0.01 * 0.01, rel=1e-6)  # homogeneous: exact up to solver tolerance
    assert res.x[:, 1].max() == pytest.approx(0.01 * lat, rel=1e-8)
    assert res.x[:, 2].max() == pytest.approx(0.01 * lat, rel=1e-8)


def test_closed_form_limits() -> None:
    # small strain: nominal stress ≈ E (λ − 1), lateral strain ≈ −ν (λ − 1)
    mu, kappa = 3.0e4, 1.5e5
    E, nu = 9 * mu * kappa / (3 * kappa + mu), (3 * kappa - 2 * mu) / (2 * (3 * kappa + mu))
    p, lat = uniaxial_neo_hookean(mu, kappa, 1.0001)
    assert p == pytest.approx(E * 1e-4, rel=1e-3)
    assert lat - 1 == pytest.approx(-nu * 1e-4, rel=1e-3)
    # Mooney-Rivlin with c01 = 0 is neo-Hookean with μ = 2 c10
    assert uniaxial(mooney_rivlin(mu / 2, 0.0, kappa), 1.5)[0] == pytest.approx(
        uniaxial_neo_hookean(mu, kappa, 1.5)[0], rel=1e-12)


@pytest.mark.parametrize("order", [1, 2])
def test_gravity_load_sums_to_weight(order: int) -> None:
    mesh = box_mesh((0.03, 0.02, 0.01), (3, 2, 2), order=order)
    m = nodal_masses(mesh, MAT)
    assert m.sum() == pytest.approx(MAT.density * 0.03 * 0.02 * 0.01, rel=1e-12)
    f = gravity_forces(mesh, MAT, (0.0, 0.0, -9.81))
    assert f.sum(axis=0) == pytest.approx([0, 0, -9.81 * m.sum()], rel=1e-12, abs=1e-15)
    # first moment: the load acts through the centroid
    assert (f[:, 2] * mesh.nodes[:, 0]).sum() / f[:, 2].sum() == pytest.approx(0.015, rel=1e-12)
