"""The layered design mesh of the sample skin: conforming columns of tets, the same outer surface and face units,
attachments that never share a tet, rest-shape derivatives checked on it, and large thickness steps that no
longer fold the skin."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from offline.design.layered import folded_prisms, layered_mesh, layered_skin_folder, prism_tets
from offline.fem import TetMesh, load_mesh
from offline.fem.mesh import boundary_faces, signed_volumes

ROOT = Path(__file__).resolve().parents[3]
SKIN = ROOT / "heads" / "sample" / "skin"


def _faces_count(tets: np.ndarray) -> np.ndarray:
    f = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    _, counts = np.unique(np.sort(f, axis=1), axis=0, return_counts=True)
    return counts


def test_prisms_of_a_grid_are_conforming_and_positive_after_orientation():
    g = np.stack(np.meshgrid(np.arange(4.0), np.arange(3.0), indexing="ij"), -1).reshape(-1, 2) * 1e-3
    idx = np.arange(12).reshape(4, 3)
    tris = np.concatenate([np.stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()], 1),
                           np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()], 1)])
    S, L = len(g), 3
    columns = np.arange(S * (L + 1)).reshape(L + 1, S).T
    nodes = np.concatenate([np.c_[g, np.full(S, -k * 1e-3)] for k in range(L + 1)])
    tets = prism_tets(tris, columns)
    assert tets.shape == (3 * len(tris) * L, 4)
    vol = signed_volumes(nodes, tets)
    assert np.all(np.abs(vol) > 0)
    assert np.isclose(np.abs(vol).sum(), 3e-3 * 2e-3 * 3e-3)  # the slab's volume: no overlap, no gap
    assert set(_faces_count(tets).tolist()) <= {1, 2}  # every interior face shared by exactly two tets


def test_sample_skin_extruded_in_two_layers(tmp_path: Path):
    report = layered_skin_folder(SKIN, tmp_path, layers=2)
    mesh = load_mesh(tmp_path / "skin.vtu")
    src = load_mesh(SKIN / "skin.vtu")
    with np.load(SKIN / "face_units.npz") as z:
        outer, offsets = np.asarray(z["surface_nodes"]), np.asarray(z["offsets"])
    with np.load(tmp_path / "face_units.npz") as z:
        assert np.array_equal(z["surface_nodes"], np.arange(len(outer)))
        assert np.array_equal(z["offsets"], offsets)
        inner = np.asarray(z["inner_nodes"])
    S = len(outer)
    assert np.allclose(np.asarray(mesh.nodes)[:S], np.asarray(src.nodes)[outer])  # same outer surface
    assert mesh.n_nodes == 3 * S and report["layers"] == 2
    assert np.all(signed_volumes(np.asarray(mesh.nodes), np.asarray(mesh.tets)) > 0)
    assert set(_faces_count(np.asarray(mesh.tets)).tolist()) <= {1, 2}
    # interior nodes: a whole layer between the surfaces (the shipped skin has 127 of 2,316)
    assert mesh.n_nodes - S - inner.size == S
    # attachments: on the inner layer only, every set present, no tet touching two of them
    label = np.full(mesh.n_nodes, -1)
    for k, (name, idx) in enumerate(mesh.node_sets.items()):
        assert idx.size > 0, name
        assert np.isin(idx, inner).all()
        label[idx] = k
    lab = label[np.asarray(mesh.tets)]
    for row in lab:
        assert len(set(row[row >= 0].tolist())) <= 1
    assert json.loads((tmp_path / "mesh_report.json").read_text())["counts"]["tets"] == mesh.n_tets
    assert 0.002 < report["thickness_m"]["median"] < 0.008
    with np.load(SKIN / "face_units.npz") as z:
        n_tri = len(z["surface_triangles"])
    assert len(boundary_faces(mesh)) > 2 * n_tri  # outer, inner and the rims' walls
    # and nowhere does the skin pass through itself (a mold could not cast it): the columns that did are shorter
    from offline.design.mesh_check import self_intersecting_pairs

    assert len(self_intersecting_pairs(np.asarray(mesh.nodes) * 1e3, boundary_faces(mesh))) == 0


def test_a_folded_column_is_untangled():
    # a 2 x 2 patch whose centre column leans across its neighbours: the build refuses nothing, it untangles
    g = np.array([[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1], [0, 2], [1, 2], [2, 2]], float) * 2e-3
    tris = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]])
    pos = np.c_[g, np.zeros(9)]
    end = pos + np.array([0, 0, -3e-3])
    end[4] += [5e-3, 0, 0]  # the centre column crosses its right neighbours
    assert folded_prisms(pos, tris, end).size > 0
    from offline.design.layered import untangle_columns

    fixed, changed = untangle_columns(pos, tris, end)
    assert folded_prisms(pos, tris, fixed).size == 0 and changed > 0


def test_columns_that_meet_across_a_fold_are_shortened_until_the_skin_no_longer_crosses_itself():
    from offline.design.layered import crossing_columns, uncross_columns

    # two strips 1 mm apart facing each other (a fold of the surface), columns 1.5 mm long: each side's column
    # ends pass through the other side
    x, z = np.meshgrid(np.arange(5.0), np.arange(3.0), indexing="ij")
    strip = np.c_[x.ravel(), np.zeros(x.size), z.ravel()] * 1e-3
    idx = np.arange(15).reshape(5, 3)
    tris = np.concatenate([np.stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()], 1),
                           np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()], 1)])
    pos = np.concatenate([strip, strip + np.array([0.5e-3, 1e-3, 0.5e-3])])  # offset: no edges shared
    tris = np.concatenate([tris, tris[:, ::-1] + 15])
    inward = np.repeat([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], 15, axis=0)
    end = pos + 1.5e-3 * inward
    assert crossing_columns(pos, tris, end).size > 0
    fixed, changed = uncross_columns(pos, tris, end)
    assert crossing_columns(pos, tris, fixed).size == 0 and changed > 0
    h = np.linalg.norm(fixed - pos, axis=1)
    assert np.all(h[crossing_columns(pos, tris, end)] < 1.5e-3) and h.max() <= 1.5e-3


def test_rest_shape_derivatives_on_the_layered_skin():
    from offline.fem import internal_forces, neo_hookean
    from offline.fem.rest_shape import mixed_stiffness

    src = load_mesh(SKIN / "skin.vtu")
    with np.load(SKIN / "face_units.npz") as z:
        lay = layered_mesh(src, z["surface_nodes"], z["surface_triangles_local"], z["inner_nodes"], layers=2)
    mesh = lay.mesh
    rng = np.random.default_rng(0)
    X = np.asarray(mesh.nodes)
    x = X @ (np.eye(3) + rng.normal(scale=0.05, size=(3, 3))).T + rng.normal(scale=1e-5, size=X.shape)
    mat = neo_hookean(3e4, 6e5)
    B = mixed_stiffness(mesh, mat, x)
    h = 1e-9
    for _ in range(2):
        dX = rng.normal(size=X.shape) * (np.arange(mesh.n_nodes) >= len(lay.thickness))[:, None]
        fp = internal_forces(TetMesh(X + h * dX, mesh.tets), mat, x)
        fm = internal_forces(TetMesh(X - h * dX, mesh.tets), mat, x)
        fd = (fp - fm).ravel() / (2 * h)
        assert np.linalg.norm(B @ dX.ravel() - fd) <= 1e-5 * np.linalg.norm(fd)


def test_large_thickness_steps_keep_the_layered_skin_unfolded(tmp_path: Path):
    """Every height at the 3 mm lower bound, or ±3 mm contrasts between neighbouring samples, fold no element of
    the two-layer skin; thinning to 3 mm folds the shipped one-tet-thick skin, and a 2 mm thickening folds it more
    than the layered one (whose thickness direction is smoothed over the face)."""
    from offline.design.face import face_warp, load_face
    from offline.fem.energy import element_min_jacobian

    layered_skin_folder(SKIN, tmp_path, layers=2)
    config = ROOT / "heads" / "sample" / "head.toml"
    inverted = {}
    for name, folder in (("shipped", None), ("layered", tmp_path)):
        face = load_face(config, folder)
        warp, h0 = face_warp(face, n_samples=40)
        sign = np.where(np.arange(warp.n_samples) % 2 == 0, 1.0, -1.0)
        steps = {"thin": np.full_like(h0, 0.003), "contrast": np.clip(h0 + 3e-3 * sign, 0.003, 0.012),
                 "thick": np.clip(h0 + 2e-3, 0.003, 0.012)}
        inverted[name] = {k: int(np.sum(element_min_jacobian(warp.mesh, warp.rest_positions(h)) <= 0))
                          for k, h in steps.items()}
    assert inverted["layered"]["thin"] == 0 and inverted["layered"]["contrast"] == 0
    assert inverted["shipped"]["thin"] > 0
    assert inverted["layered"]["thick"] < inverted["shipped"]["thick"]


def test_warp_on_layered_skin_scales_each_column(tmp_path: Path):
    """All sample heights × 1.5 move every free inner node by half its column's height, a mid-layer node by a
    quarter, and no attachment node; the rest shape at the reference heights is the mesh itself."""
    from offline.design.face import face_warp, load_face

    layered_skin_folder(SKIN, tmp_path, layers=2)
    face = load_face(ROOT / "heads" / "sample" / "head.toml", tmp_path)
    warp, h0 = face_warp(face, n_samples=20)
    X0 = np.asarray(face.mesh.nodes)
    assert np.allclose(warp.rest_positions(h0), X0)
    with np.load(tmp_path / "columns.npz") as z:
        height, col = np.asarray(z["thickness"]), np.asarray(z["column"])
    move = np.linalg.norm(warp.rest_positions(1.5 * h0) - X0, axis=1)
    S = len(face.outer)
    held = np.isin(col, col[face.locked])
    inner = np.arange(2 * S, 3 * S)
    mid = np.arange(S, 2 * S)
    assert np.allclose(move[inner][~held[inner]], 0.5 * height[inner][~held[inner]], rtol=1e-9)
    assert np.allclose(move[mid][~held[mid]], 0.25 * height[mid][~held[mid]], rtol=1e-9)
    assert np.all(move[held] == 0) and np.all(move[:S] == 0)


@pytest.mark.slow
def test_thickness_gradient_on_the_layered_head_matches_finite_differences(tmp_path: Path):
    """dE/dh of the thickness objective on the two-layer head (one pose, 5 samples, region weights) by the
    adjoint against central differences of exact equilibria."""
    from offline.design.face import face_warp, load_face
    from offline.design.thickness import Pose, ThicknessProblem, adjoint_gradient, solve_poses
    from offline.fem.solve import SolverOptions

    layered_skin_folder(SKIN, tmp_path, layers=2)
    face = load_face(ROOT / "heads" / "sample" / "head.toml", tmp_path)
    warp, h0 = face_warp(face, n_samples=5)
    space = face.space
    p = space.expand(space.project(space.reduce(space.neutral + 0.15 * (space.hi - space.lo))))
    target = np.asarray(face.mesh.nodes)[face.outer] + 1e-3
    w = np.where(np.isin(face.outer, face.locked), 0.0, 1.0)
    problem = ThicknessProblem(warp, face.skin.material, (Pose(space.boundary(p), target),), face.outer, 0.003,
                               0.012, region_weights=w, solver=SolverOptions(tol_force=1e-10, load_steps=1))
    h = np.clip(h0, 0.0031, 0.0119) * (1 + 0.05 * np.arange(5) / 5)
    state = solve_poses(problem, h)
    g = adjoint_gradient(problem, state)
    eps = 1e-7
    for s in range(5):
        e = np.zeros_like(h)
        e[s] = eps
        fd = (solve_poses(problem, h + e, state.xs).value - solve_poses(problem, h - e, state.xs).value) / (2 * eps)
        assert g[s] == pytest.approx(fd, rel=1e-4, abs=1e-6 * np.abs(g).max())


def test_clone_refuses_a_single_layer_and_negative_noise(tmp_path: Path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "likeness.cli", "offline", "clone", "--config",
                               str(ROOT / "heads" / "sample" / "head.toml"), "--out", str(tmp_path), *args],
                              capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)

    bad_layers = cli("--layers", "1")
    assert bad_layers.returncode == 2 and "--layers 1" in bad_layers.stderr
    bad_noise = cli("--ground-truth-test", "--noise-mm", "-1")
    assert bad_noise.returncode == 2 and "--noise-mm" in bad_noise.stderr
