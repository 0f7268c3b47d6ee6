"""The discretization refinement study: level meshes, the displacement comparison, the pose set, and a patch test
(an affine boundary motion is reproduced exactly by every level, so the study must report no change)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from offline.fem import Dirichlet, SolverOptions, box_mesh, neo_hookean_from_E_nu, solve_static
from offline.fem.mesh import boundary_faces
from offline.refinement import build_levels, compare_displacements, representative_poses, summarize

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def _box_levels(names):
    mesh = box_mesh((0.02, 0.02, 0.02), (2, 2, 2))
    tris = boundary_faces(mesh)
    outer = np.unique(tris)
    return mesh, outer, build_levels(mesh, outer, tris, names)


def test_levels_keep_the_coarse_nodes_first_and_grow_as_stated():
    mesh, _, lv = _box_levels(["L0", "P2", "L1", "L1P2", "L2"])
    n = mesh.n_nodes
    for name, m in lv.items():
        np.testing.assert_array_equal(np.asarray(m.nodes)[:n], np.asarray(mesh.nodes), err_msg=name)
        # node sets keep their coarse members and gain only nodes on the same face
        assert set(np.asarray(mesh.node_sets["x1"]).tolist()) <= set(np.asarray(m.node_sets["x1"]).tolist())
        assert np.allclose(np.asarray(m.nodes)[m.node_sets["x1"], 0], 0.02)
    assert lv["P2"].order == 2 and lv["P2"].n_tets == mesh.n_tets
    assert lv["L1"].order == 1 and lv["L1"].n_tets == 8 * mesh.n_tets
    assert lv["L1P2"].order == 2 and lv["L1P2"].n_tets == 8 * mesh.n_tets
    assert lv["L2"].n_tets == 64 * mesh.n_tets
    # L1 has exactly the nodes of P2 (corners + mid-edges), L2 those of L1P2
    assert lv["L1"].n_nodes == lv["P2"].n_nodes and lv["L2"].n_nodes == lv["L1P2"].n_nodes


def test_unknown_or_nonlinear_start_level_is_refused():
    mesh = box_mesh((0.01, 0.01, 0.01), (1, 1, 1))
    tris = boundary_faces(mesh)
    with pytest.raises(ValueError, match="unknown refinement level"):
        build_levels(mesh, np.unique(tris), tris, ["L0", "L3"])
    with pytest.raises(ValueError, match="linear mesh"):
        build_levels(box_mesh((0.01, 0.01, 0.01), (1, 1, 1), order=2), np.unique(tris), tris, ["L0"])


def test_comparison_on_a_known_change():
    u = np.zeros((5, 3))
    u[:, 0] = [1e-3, 2e-3, 3e-3, 4e-3, 10e-3]  # fine displacement magnitudes 1..4 and 10 mm
    coarse = u.copy()
    coarse[2] += [0.0, 3e-4, 4e-4]  # 0.5 mm off at vertex 2
    labels = np.array([0, 0, 1, 1, 2])
    r = compare_displacements(coarse, u, ("jaw", "lip_corner_l", "free"), labels)
    assert r["max_m"] == pytest.approx(5e-4) and r["max_vertex"] == 2 and r["max_region"] == "lip_corner_l"
    assert r["mean_m"] == pytest.approx(1e-4)
    assert r["displacement_max_m"] == pytest.approx(1e-2)
    assert r["relative_max"] == pytest.approx(0.05)
    assert r["relative_mean"] == pytest.approx(1e-4 / 4e-3)
    assert r["relative_max_pointwise"] == pytest.approx(5e-4 / 3e-3)
    assert r["per_region"]["jaw"]["max_m"] == 0.0 and r["per_region"]["lip_corner_l"]["mean_m"] == pytest.approx(2.5e-4)
    s = summarize({"L0->P2": [{**r, "pose": "smile_l"}, None]})["L0->P2"]
    assert s["poses"] == 1 and s["max_pose"] == "smile_l" and s["max_m"] == pytest.approx(5e-4)
    at_rest = compare_displacements(np.zeros((5, 3)), np.zeros((5, 3)), ("free",), np.zeros(5, dtype=int))
    assert at_rest["relative_mean"] is None and at_rest["max_m"] == 0.0
    with pytest.raises(ValueError, match="displacements"):
        compare_displacements(np.zeros((4, 3)), np.zeros((5, 3)), ("free",), np.zeros(5, dtype=int))


def test_representative_poses_of_the_sample_head():
    head = load_head(SAMPLE)
    P, labels = representative_poses(head, 6, seed=0)
    assert labels[:4] == ["neutral", "jaw_open", "smile_l", "smile_r"] and len(P) == 6
    names = head.actuator_names
    assert P[1, names.index("jaw")] == pytest.approx(head.actuators[names.index("jaw")].max)
    assert P[2, names.index("lip_corner_l_up")] > 0 and P[2, names.index("lip_corner_r_up")] == 0
    np.testing.assert_array_equal(P, representative_poses(head, 6, seed=0)[0])
    assert not np.array_equal(P[4:], representative_poses(head, 6, seed=1)[0][4:])


def test_patch_test_every_level_reproduces_an_affine_motion():
    """All boundary nodes moved by one affine map: the exact solution is that map, on every level; the study's
    comparison at the coarse outer vertices must report (numerically) zero change, and a wrong level would not."""
    mesh, outer, lv = _box_levels(["L0", "P2", "L1"])
    F = np.array([[1.08, 0.03, 0.0], [0.0, 0.97, 0.02], [0.01, 0.0, 1.02]])
    material = neo_hookean_from_E_nu(78e3, 0.45)
    rest = np.asarray(mesh.nodes)[outer]
    disp = {}
    for name, m in lv.items():
        X = np.asarray(m.nodes)
        b = np.unique(np.concatenate([m.node_sets[f] for f in ("x0", "x1", "y0", "y1", "z0", "z1")]))
        sol = solve_static(m, material, Dirichlet(b, X[b] @ F.T), options=SolverOptions(backend="superlu"))
        assert sol.converged
        x = np.asarray(sol.x).reshape(-1, 3)
        np.testing.assert_allclose(x, X @ F.T, atol=1e-9)  # interior nodes follow the affine map too
        disp[name] = x[: mesh.n_nodes][outer] - rest
    labels = np.zeros(len(outer), dtype=int)
    for a, b in (("L0", "P2"), ("P2", "L1")):
        r = compare_displacements(disp[a], disp[b], ("surface",), labels)
        assert r["max_m"] < 1e-9 and r["displacement_max_m"] > 1e-3
    wrong = disp["L1"].copy()
    wrong[0, 1] += 1e-4
    assert compare_displacements(disp["L0"], wrong, ("surface",), labels)["max_m"] == pytest.approx(1e-4)
