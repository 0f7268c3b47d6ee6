"""Mesh generators, quadratic conversion, boundary extraction, quality and file round trips."""

from __future__ import annotations

import numpy as np
import pytest

from offline.fem import (
    TetMesh,
    boundary_faces,
    box_mesh,
    cylinder_mesh,
    load_mesh,
    save_mesh,
    tet_quality,
    to_quadratic,
)
from offline.fem.mesh import signed_volumes


def test_box_mesh_is_conforming_positive_and_fills_the_box() -> None:
    mesh = box_mesh((0.03, 0.02, 0.01), (3, 2, 2))
    assert mesh.n_nodes == 4 * 3 * 3 and mesh.n_tets == 6 * 12 and mesh.order == 1
    vol = signed_volumes(mesh.nodes, mesh.tets)
    assert vol.min() > 0 and vol.sum() == pytest.approx(0.03 * 0.02 * 0.01, rel=1e-12)
    faces = boundary_faces(mesh)
    # conforming: only the outer surface is left, 2 triangles per boundary quad
    assert len(faces) == 2 * 2 * (3 * 2 + 3 * 2 + 2 * 2)
    # outward orientation: divergence theorem, (1/3) Σ area·n·centroid = volume
    p = mesh.nodes[faces]
    n2 = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.sum(np.einsum("ij,ij->i", n2, p.mean(axis=1))) / 6.0 == pytest.approx(vol.sum(), rel=1e-12)
    assert np.all(mesh.nodes[mesh.node_sets["x1"], 0] == pytest.approx(0.03))
    assert len(mesh.node_sets["z0"]) == 4 * 3


def test_to_quadratic_shares_mid_edge_nodes_and_extends_sets() -> None:
    lin = box_mesh((0.02, 0.01, 0.01), (2, 1, 1))
    quad = to_quadratic(lin)
    edges = {tuple(sorted(e)) for t in lin.tets for e in t[[[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]]}
    assert quad.order == 2 and quad.n_nodes == lin.n_nodes + len(edges)
    t = quad.tets
    for m, (i, j) in enumerate([(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]):
        assert np.allclose(quad.nodes[t[:, 4 + m]], 0.5 * (quad.nodes[t[:, i]] + quad.nodes[t[:, j]]))
    x1 = quad.node_sets["x1"]
    assert np.allclose(quad.nodes[x1, 0], 0.02) and len(x1) > len(lin.node_sets["x1"])
    assert np.sum(np.isclose(quad.nodes[:, 0], 0.02)) == len(x1)
    assert box_mesh((0.02, 0.01, 0.01), (2, 1, 1), order=2).n_nodes == quad.n_nodes


def test_cylinder_mesh_volume_and_sets() -> None:
    mesh = cylinder_mesh(0.01, 0.02, 6, 4)
    vol = signed_volumes(mesh.nodes, mesh.tets)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(np.pi * 0.01**2 * 0.02, rel=0.02)
    assert np.allclose(mesh.nodes[mesh.node_sets["top"], 2], 0.02)
    assert np.linalg.norm(mesh.nodes[:, :2], axis=1).max() == pytest.approx(0.01, rel=1e-9)
    assert tet_quality(mesh).min() > 0.3


def test_tet_quality_regular_and_degenerate() -> None:
    reg = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    tet = np.array([[0, 1, 2, 3]])
    if signed_volumes(reg, tet)[0] < 0:
        tet = tet[:, [0, 2, 1, 3]]
    assert tet_quality(TetMesh(reg, tet))[0] == pytest.approx(1.0, rel=1e-12)
    flat = reg.copy()
    flat[3] = (flat[0] + flat[1] + flat[2]) / 3 + np.array([0, 0, 1e-9])
    assert tet_quality(TetMesh(flat, np.array([[0, 1, 2, 3]])))[0] < 1e-6


@pytest.mark.parametrize("order", [1, 2])
def test_save_load_round_trip(tmp_path, order: int) -> None:
    mesh = box_mesh((0.02, 0.01, 0.01), (2, 1, 1), order=order).with_node_sets(patch=[0, 3, 5])
    path = tmp_path / "sub" / "m.vtu"
    save_mesh(path, mesh)
    back = load_mesh(path)
    assert back.order == order
    assert np.array_equal(back.tets, mesh.tets) and np.allclose(back.nodes, mesh.nodes)
    assert set(back.node_sets) == set(mesh.node_sets)
    for k in mesh.node_sets:
        assert np.array_equal(back.node_sets[k], mesh.node_sets[k])
    assert [p.name for p in path.parent.iterdir()] == ["m.vtu"]  # no temp files left


def test_mesh_is_immutable_and_validates() -> None:
    mesh = box_mesh((1, 1, 1), (1, 1, 1))
    with pytest.raises(ValueError):
        mesh.nodes[0, 0] = 5.0
    with pytest.raises(ValueError, match="out of range"):
        TetMesh(np.zeros((3, 3)), np.array([[0, 1, 2, 3]]))
    with pytest.raises(ValueError, match="node set 'bad'"):
        mesh.with_node_sets(bad=[999])
    with pytest.raises(ValueError, match=r"shape \(M, 4\)"):
        TetMesh(np.zeros((4, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="divisions"):
        box_mesh((1, 1, 1), (0, 1, 1))


def test_meshes_materials_and_results_pickle() -> None:
    import pickle

    from offline.fem import SolverOptions, fixed, neo_hookean, solve_static

    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1), order=2)
    back = pickle.loads(pickle.dumps(mesh))
    assert np.array_equal(back.tets, mesh.tets) and set(back.node_sets) == set(mesh.node_sets)
    mat = pickle.loads(pickle.dumps(neo_hookean(1e4, 1e5)))
    assert mat.params["mu"] == 1e4
    res = solve_static(mesh, mat, fixed(mesh, "z0"), options=SolverOptions(backend="superlu", gravity=(0, 0, -9.81)))
    res2 = pickle.loads(pickle.dumps(res))
    assert np.array_equal(res2.x, res.x) and res2.timings["total"] == res.timings["total"]
