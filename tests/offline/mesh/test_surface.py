"""Surface utilities and the skin shell on synthetic geometry: loops, closest points, intersections, stitching."""

from __future__ import annotations

import numpy as np
import pytest

from offline.mesh.shell import INNER, OUTER, WALL, ShellError, ShellParams, build_shell, check_shell, stitch
from offline.mesh.surface import (
    boundary_loops,
    closed_manifold_problems,
    closest_points,
    euler_characteristic,
    self_intersections,
)


def grid_with_hole(n: int = 12, hole: tuple[int, int] = (4, 7), size: float = 0.1, bulge: float = 0.02):
    """A gently domed (n x n)-quad sheet facing +z with a square hole of quads removed."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    Z = bulge * (1 - (X**2 + Y**2) / (size**2 / 2))
    verts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    tris = []
    for i in range(n):
        for j in range(n):
            if hole[0] <= i < hole[1] and hole[0] <= j < hole[1]:
                continue
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            tris += [[a, b, c], [a, c, d]]
    return verts, np.asarray(tris, dtype=np.int64)


def test_boundary_loops_of_sheet_with_hole() -> None:
    _v, t = grid_with_hole()
    loops = boundary_loops(t)
    assert [len(loop) for loop in loops] == [48, 12]
    assert euler_characteristic(t) == 0  # disk with one hole


def test_boundary_loops_reject_pinched_boundary() -> None:
    t = np.array([[0, 1, 2], [0, 3, 4]])  # two triangles touching at one vertex
    with pytest.raises(ValueError, match="non-manifold"):
        boundary_loops(t)


def test_closest_points_match_brute_force() -> None:
    v, t = grid_with_hole()
    rng = np.random.default_rng(1)
    pts = rng.uniform([-0.05, -0.05, -0.02], [0.05, 0.05, 0.04], size=(200, 3))
    tri, bary, dist = closest_points(v, t, pts, candidates=len(t))
    q = np.einsum("pk,pkj->pj", bary, v[t[tri]])
    assert np.allclose(np.linalg.norm(q - pts, axis=1), dist)
    assert (bary >= -1e-12).all() and np.allclose(bary.sum(axis=1), 1.0)
    # brute force over dense samples of every triangle: nothing is closer than the reported point
    w = rng.dirichlet(np.ones(3), size=64)
    samples = np.einsum("sk,tkj->tsj", w, v[t]).reshape(-1, 3)
    brute = np.min(np.linalg.norm(samples[None, :, :] - pts[:, None, :], axis=2), axis=1)
    assert (dist <= brute + 1e-12).all()


def test_self_intersections_found_and_not_invented() -> None:
    v, t = grid_with_hole()
    assert len(self_intersections(v, t)) == 0
    # a separate triangle piercing the sheet
    extra = np.array([[0.03, 0.041, -0.02], [0.033, 0.03, 0.05], [0.027, 0.027, 0.05]])
    v2 = np.concatenate([v, extra])
    t2 = np.concatenate([t, [[len(v), len(v) + 1, len(v) + 2]]])
    hits = self_intersections(v2, t2)
    assert len(t) in hits
    assert len(hits) >= 2


def test_shell_of_sheet_is_watertight_outward_and_of_right_genus() -> None:
    v, t = grid_with_hole()
    loops = tuple(boundary_loops(t))
    shell = build_shell(v, t, loops, ShellParams(thickness=0.004, normal_smoothing=5))
    assert closed_manifold_problems(shell.triangles) == []
    assert euler_characteristic(shell.triangles) == 0  # thickened annulus = torus
    area = 0.1 * 0.1 * (1 - 9 / 144)
    assert shell.volume == pytest.approx(area * 0.004, rel=0.1)
    assert set(np.unique(shell.labels)) == {OUTER, INNER, WALL}
    assert np.allclose(shell.inner_vertices, shell.vertices[len(v):])
    assert len(shell.inner_triangles) == len(t)


def test_check_shell_rejects_a_hole_and_a_flip() -> None:
    v, t = grid_with_hole()
    loops = tuple(boundary_loops(t))
    shell = build_shell(v, t, loops, ShellParams(thickness=0.004, normal_smoothing=5))
    broken = type(shell)(shell.vertices, shell.triangles[1:], shell.labels[1:], shell.n_outer, 0, 0)
    with pytest.raises(ShellError, match="holes"):
        check_shell(broken, n_loops=2)
    flipped = type(shell)(shell.vertices, shell.triangles[:, ::-1], shell.labels, shell.n_outer, 0, 0)
    with pytest.raises(ShellError, match="volume"):
        check_shell(flipped, n_loops=2)


def test_stitch_labels_and_orientation() -> None:
    v, t = grid_with_hole(n=4, hole=(1, 3))
    loops = tuple(boundary_loops(t))
    tris, labels = stitch(t, loops, len(v))
    assert (labels == WALL).sum() == 2 * sum(len(loop) for loop in loops)
    assert closed_manifold_problems(tris) == []
