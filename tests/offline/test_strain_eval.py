"""Tools behind the strain guard's checks: the uniform mesh refinement of the measure's refinement study."""

from __future__ import annotations

import numpy as np

from offline.fem import boundary_faces, box_mesh
from offline.fem.mesh import signed_volumes
from offline.strain_eval import refine_uniform


def top_surface(mesh):
    bf = boundary_faces(mesh)
    z1 = np.zeros(mesh.n_nodes, dtype=bool)
    z1[mesh.node_sets["z1"]] = True
    tris = bf[z1[bf].all(axis=1)]
    outer = np.unique(tris)
    return outer, tris


def test_uniform_refinement_keeps_the_geometry_and_halves_the_edges():
    mesh = box_mesh((0.03, 0.02, 0.006), (3, 2, 1))
    outer, tris = top_surface(mesh)
    fine, fine_outer, fine_tris = refine_uniform(mesh, outer, tris)
    assert fine.n_tets == 8 * mesh.n_tets
    vol = signed_volumes(np.asarray(fine.nodes), np.asarray(fine.tets))
    assert np.all(vol > 0)
    assert abs(vol.sum() - 0.03 * 0.02 * 0.006) < 1e-15
    # The outer surface: old vertices first, in order; four triangles per old one, the same area.
    assert np.array_equal(fine_outer[: len(outer)], outer) and len(fine_tris) == 4 * len(tris)
    X = np.asarray(fine.nodes)
    area = 0.5 * np.linalg.norm(np.cross(X[fine_tris[:, 1]] - X[fine_tris[:, 0]],
                                         X[fine_tris[:, 2]] - X[fine_tris[:, 0]]), axis=1)
    assert abs(area.sum() - 0.03 * 0.02) < 1e-15 and np.all(area > 0)
    # Node sets keep the mid-edge nodes of their own edges: the top face gains its edge midpoints.
    assert np.all(np.abs(X[fine.node_sets["z1"], 2] - 0.006) < 1e-15)
    assert len(fine.node_sets["z1"]) == (2 * 3 + 1) * (2 * 2 + 1)
