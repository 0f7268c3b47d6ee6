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


def test_quadratic_mesh_is_refused():
    mesh = to_quadratic(box_mesh((0.01, 0.01, 0.01), (1, 1, 1)))
    with pytest.raises(ValueError, match="linear"):
        mixed_stiffness(mesh, neo_hookean(3e4, 6e5), mesh.nodes)
