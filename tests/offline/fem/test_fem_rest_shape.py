"""Rest-shape derivatives of the FEM energy and forces against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem import TetMesh, box_mesh, internal_forces, mooney_rivlin, neo_hookean, to_quadratic, total_energy
from offline.fem.rest_shape import mixed_stiffness, rest_energy_gradient


def _deformed(seed: int = 0):
    rng = np.random.default_rng(seed)
    mesh = box_mesh((0.02, 0.012, 0.006), (3, 2, 2))
    nodes = np.asarray(mesh.nodes) + rng.normal(scale=4e-4, size=mesh.nodes.shape)  # irregular rest shape
    mesh = TetMesh(nodes, mesh.tets, mesh.node_sets)
    A = np.eye(3) + rng.normal(scale=0.15, size=(3, 3))
    x = nodes @ A.T + rng.normal(scale=3e-4, size=nodes.shape)
    return mesh, x


@pytest.mark.parametrize("material", [neo_hookean(3e4, 6e5), mooney_rivlin(1e4, 3e3, 5e5)])
def test_rest_energy_gradient_matches_finite_differences(material):
    mesh, x = _deformed()
    g = rest_energy_gradient(mesh, material, x)
    rng = np.random.default_rng(1)
    h = 1e-7
    for _ in range(5):
        dX = rng.normal(size=mesh.nodes.shape)
        plus = TetMesh(np.asarray(mesh.nodes) + h * dX, mesh.tets)
        minus = TetMesh(np.asarray(mesh.nodes) - h * dX, mesh.tets)
        fd = (total_energy(plus, material, x) - total_energy(minus, material, x)) / (2 * h)
        assert np.sum(g * dX) == pytest.approx(fd, rel=1e-6)


@pytest.mark.parametrize("material", [neo_hookean(3e4, 6e5), mooney_rivlin(1e4, 3e3, 5e5)])
def test_mixed_stiffness_matches_finite_differences(material):
    mesh, x = _deformed(2)
    B = mixed_stiffness(mesh, material, x)
    rng = np.random.default_rng(3)
    h = 1e-8
    for _ in range(4):
        dX = rng.normal(size=mesh.nodes.shape)
        plus = TetMesh(np.asarray(mesh.nodes) + h * dX, mesh.tets)
        minus = TetMesh(np.asarray(mesh.nodes) - h * dX, mesh.tets)
        fd = (internal_forces(plus, material, x) - internal_forces(minus, material, x)).ravel() / (2 * h)
        an = B @ dX.ravel()
        assert np.linalg.norm(an - fd) <= 1e-6 * np.linalg.norm(fd)


def test_rest_energy_gradient_is_zero_at_rest():
    """At x = X the energy is stationary in X too (Ψ = 0 and P = 0 at F = I)."""
    material = neo_hookean(3e4, 6e5)
    mesh, _ = _deformed(4)
    g = rest_energy_gradient(mesh, material, mesh.nodes)
    assert np.abs(g).max() < 1e-12


def test_quadratic_rest_energy_gradient_is_zero_at_rest():
    mesh, _ = _deformed_quadratic(8)
    g = rest_energy_gradient(mesh, neo_hookean(3e4, 6e5), mesh.nodes)
    assert np.abs(g).max() < 1e-12


def _deformed_quadratic(seed: int = 5):
    """A quadratic mesh with curved (perturbed) rest edges and a smooth non-affine deformation."""
    rng = np.random.default_rng(seed)
    mesh = to_quadratic(box_mesh((0.02, 0.012, 0.006), (2, 2, 1)))
    nodes = np.asarray(mesh.nodes) + rng.normal(scale=2e-4, size=mesh.nodes.shape)
    mesh = TetMesh(nodes, mesh.tets, mesh.node_sets)
    A = np.eye(3) + rng.normal(scale=0.12, size=(3, 3))
    x = nodes @ A.T + 0.02 * np.sin(40 * nodes[:, [1, 2, 0]]) * 1e-1 + rng.normal(scale=1e-4, size=nodes.shape)
    return mesh, x


@pytest.mark.parametrize("material", [neo_hookean(3e4, 6e5), mooney_rivlin(1e4, 3e3, 5e5)])
def test_quadratic_rest_derivatives_match_finite_differences(material):
    mesh, x = _deformed_quadratic()
    g = rest_energy_gradient(mesh, material, x)
    B = mixed_stiffness(mesh, material, x)
    rng = np.random.default_rng(6)
    for _ in range(4):
        dX = rng.normal(size=mesh.nodes.shape)
        h = 1e-8
        plus = TetMesh(np.asarray(mesh.nodes) + h * dX, mesh.tets)
        minus = TetMesh(np.asarray(mesh.nodes) - h * dX, mesh.tets)
        fd_e = (total_energy(plus, material, x) - total_energy(minus, material, x)) / (2 * h)
        assert np.sum(g * dX) == pytest.approx(fd_e, rel=1e-6)
        fd = (internal_forces(plus, material, x) - internal_forces(minus, material, x)).ravel() / (2 * h)
        assert np.linalg.norm(B @ dX.ravel() - fd) <= 1e-6 * np.linalg.norm(fd)


def test_general_kernels_agree_with_the_linear_ones():
    """The isoparametric kernels (used for quadratic tets) give the linear-tet closed forms on a linear mesh."""
    from offline.fem.rest_shape import _iso_gradient_kernel, _iso_mixed_kernel, _reference

    material = neo_hookean(3e4, 6e5)
    mesh, x = _deformed(7)
    w, dN = _reference(1)
    tets = np.asarray(mesh.tets)
    g = _iso_gradient_kernel(np.asarray(mesh.nodes), x, tets, dN, w, material.coefficients)
    assert np.allclose(g, rest_energy_gradient(mesh, material, x), rtol=1e-10, atol=1e-14)
    buf = np.empty((mesh.n_tets, 12, 12))
    _iso_mixed_kernel(np.asarray(mesh.nodes), x, tets, dN, w, material.coefficients, buf)
    from offline.fem.rest_shape import _mixed_blocks_kernel

    ref = np.empty_like(buf)
    _mixed_blocks_kernel(np.asarray(mesh.nodes), x, tets, material.coefficients, ref)
    assert np.abs(buf - ref).max() <= 1e-10 * np.abs(ref).max()
