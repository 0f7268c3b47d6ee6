"""Finite-difference checks of the energy kernels: gradient vs energy, Hessian vs gradient, kernel vs NumPy stress."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem import (
    box_mesh,
    deformation_gradients,
    first_piola,
    internal_forces,
    mooney_rivlin,
    neo_hookean,
    stiffness,
    total_energy,
    yeoh,
)
from offline.fem.energy import _mesh_data

MATERIALS = {
    "neo_hookean": neo_hookean(3.0e4, 4.0e5),
    "mooney_rivlin": mooney_rivlin(1.2e4, 3.0e3, 4.0e5),
    "yeoh": yeoh(1.5e4, -8.0e2, 1.5e2, 4.0e5),
}


def _deformed(mesh, seed: int) -> np.ndarray:
    """A random, well-conditioned deformation: affine stretch/shear plus small nodal noise."""
    rng = np.random.default_rng(seed)
    A = np.eye(3) + 0.15 * rng.standard_normal((3, 3))
    X = np.asarray(mesh.nodes)
    h = 0.01 / 2
    return X @ A.T + 0.05 * h * rng.standard_normal(X.shape)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_gradient_and_hessian_match_finite_differences(name: str, order: int) -> None:
    mat = MATERIALS[name]
    mesh = box_mesh((0.01, 0.01, 0.01), (2, 2, 1), order=order)
    x = _deformed(mesh, seed=3 + order)
    rng = np.random.default_rng(11)
    f = internal_forces(mesh, mat, x)
    K = stiffness(mesh, mat, x)
    assert abs(K - K.T).max() <= 1e-9 * abs(K).max()
    for _ in range(3):
        d = rng.standard_normal(x.shape)
        d /= np.linalg.norm(d)
        h = 1e-6 * 0.01
        fd_grad = (total_energy(mesh, mat, x + h * d) - total_energy(mesh, mat, x - h * d)) / (2 * h)
        assert fd_grad == pytest.approx(float(np.sum(f * d)), rel=1e-6, abs=1e-9 * np.linalg.norm(f))
        fd_hess = (internal_forces(mesh, mat, x + h * d) - internal_forces(mesh, mat, x - h * d)).ravel() / (2 * h)
        Kd = K @ d.ravel()
        assert np.linalg.norm(fd_hess - Kd) <= 1e-5 * np.linalg.norm(Kd)


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_kernel_forces_match_numpy_first_piola(name: str) -> None:
    """Linear tets: f_a = Σ_e V_e P(F_e) ∇N_a, with P from the independent NumPy reference."""
    mat = MATERIALS[name]
    mesh = box_mesh((0.02, 0.01, 0.01), (2, 1, 1))
    x = _deformed(mesh, seed=7)
    F = deformation_gradients(mesh, x)[:, 0]
    P = first_piola(mat, F)
    d = _mesh_data(mesh)
    fe = np.einsum("m,mij,maj->mai", d.wdet[:, 0], P, d.dNdX[:, 0])
    ref = np.zeros_like(x)
    np.add.at(ref, np.asarray(mesh.tets), fe)
    assert np.allclose(internal_forces(mesh, mat, x), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def test_projected_stiffness_is_psd_and_unchanged_when_already_psd() -> None:
    mat = MATERIALS["neo_hookean"]
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    # Strong compression makes some element Hessians indefinite.
    x = np.asarray(mesh.nodes) * np.array([1.0, 1.0, 0.35])
    x[:, 0] += 0.4 * x[:, 2]
    K = stiffness(mesh, mat, x).toarray()
    Kp = stiffness(mesh, mat, x, project_psd=True).toarray()
    assert np.linalg.eigvalsh(Kp).min() >= -1e-9 * np.abs(Kp).max()
    assert np.linalg.eigvalsh(K).min() < -1e-6 * np.abs(K).max()  # the test would be vacuous otherwise
    # At rest each element Hessian is PSD: projection changes nothing.
    X = np.asarray(mesh.nodes)
    assert np.allclose(stiffness(mesh, mat, X, True).toarray(), stiffness(mesh, mat, X).toarray(), atol=1e-6)


def test_material_tangent_projection_clamps_negative_eigenvalues_only() -> None:
    """Each quadrature point's 9 x 9 tangent is projected as an eigenvalue clamp would (NumPy reference); definite
    ones are left as they are."""
    from offline.fem.energy import _project_psd_small

    rng = np.random.default_rng(11)
    for k in range(200):
        Q, _ = np.linalg.qr(rng.normal(size=(9, 9)))
        lam = rng.uniform(0.1, 5.0, 9)
        if k % 2:
            lam[rng.choice(9, size=1 + k % 4, replace=False)] *= -1.0
        A = (Q * lam) @ Q.T
        ref = (Q * np.maximum(lam, 0.0)) @ Q.T
        got = A.copy()
        assert _project_psd_small(got) == bool(k % 2)
        assert np.allclose(got, ref, atol=1e-12 * np.abs(A).max())


def test_projected_quadratic_element_hessians_are_psd() -> None:
    """Quadratic tets under strong shear and compression: every projected element Hessian is PSD, and the assembled
    tangent too."""
    from offline.fem import energy as en

    mat = MATERIALS["neo_hookean"]
    mesh = box_mesh((0.01, 0.01, 0.01), (2, 1, 1), order=2)
    x = np.asarray(mesh.nodes) * np.array([1.0, 1.0, 0.35])
    x[:, 0] += 0.4 * x[:, 2]
    d = _mesh_data(mesh)
    nd = 3 * mesh.tets.shape[1]
    He = np.empty((mesh.n_tets, nd, nd))
    n_proj = en._element_hessians(x, mesh.tets, d.dNdX, d.wdet, mat.coefficients, 0, en.PROJECT_QUADRATURE, He, 1)
    assert n_proj > 0
    for h in He:
        assert np.linalg.eigvalsh(h).min() >= -1e-9 * np.abs(h).max()
    Kp = stiffness(mesh, mat, x, project_psd=True).toarray()
    assert np.linalg.eigvalsh(Kp).min() >= -1e-9 * np.abs(Kp).max()


def test_energy_is_infinite_for_inverted_elements() -> None:
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    x = np.asarray(mesh.nodes) * np.array([1.0, 1.0, -1.0])
    assert total_energy(mesh, MATERIALS["neo_hookean"], x) == np.inf


@pytest.mark.parametrize("order", [1, 2])
def test_coloured_assembly_matches_the_element_by_element_sum(order: int) -> None:
    """The stiffness added colour by colour (parallel, straight into the matrix) equals a plain sum of element
    Hessians; the colours share no node."""
    from offline.fem import energy as en

    mat = MATERIALS["neo_hookean"]
    mesh = box_mesh((0.01, 0.01, 0.01), (3, 2, 2), order=order)
    x = _deformed(mesh, 3)
    ptr, elems = en._colors(mesh)
    tets = np.asarray(mesh.tets)
    assert sorted(elems.tolist()) == list(range(mesh.n_tets))
    for c in range(len(ptr) - 1):
        nodes = tets[elems[ptr[c]:ptr[c + 1]]].ravel()
        assert np.unique(nodes).size == nodes.size  # no node twice within one colour
    for name, project in ((False, en.PROJECT_NONE), ("quadrature", en.PROJECT_QUADRATURE),
                          ("element", en.PROJECT_ELEMENT)):
        K = stiffness(mesh, mat, x, project_psd=name).toarray()
        nd = 3 * tets.shape[1]
        He = np.empty((mesh.n_tets, nd, nd))
        d = _mesh_data(mesh)
        en._element_hessians(x, mesh.tets, d.dNdX, d.wdet, mat.coefficients, 0, project, He, 1)
        dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(mesh.n_tets, nd)
        ref = np.zeros_like(K)
        for e in range(mesh.n_tets):
            ref[np.ix_(dofs[e], dofs[e])] += He[e]
        assert np.allclose(K, ref, rtol=1e-12, atol=1e-9 * np.abs(ref).max())
