"""Attachment node sets grown and shrunk by whole rings on a known surface: the top of a structured box, whose
triangles (Kuhn subdivision, every quad cut along the same diagonal) give each inner vertex six neighbours: the
four grid neighbours and the diagonal pair (i+1, j+1), (i−1, j−1)."""

from __future__ import annotations

import numpy as np
import pytest

from offline.design.attachment_rings import AttachmentRings, min_nodes
from offline.fem.mesh import box_mesh

N = 12  # grid cells along x and y on the top face (13 x 13 vertices)


def _top(mesh) -> tuple[np.ndarray, dict[tuple[int, int], int]]:
    X = np.asarray(mesh.nodes)
    top = np.asarray(mesh.node_sets["z1"])
    h = 1.0 / N
    ij = {(round(float(X[n, 0]) / h), round(float(X[n, 1]) / h)): int(n) for n in top}
    return top, ij


def _square(ij: dict, i0: int, i1: int, j0: int, j1: int) -> np.ndarray:
    return np.array(sorted(ij[(i, j)] for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)))


@pytest.fixture(scope="module")
def box():
    mesh = box_mesh((1.0, 1.0, 0.2), (N, N, 2))
    top, ij = _top(mesh)
    sets = {"patch": _square(ij, 4, 8, 4, 8),  # 5 x 5 in the middle
            "corner": _square(ij, 0, 1, 0, 1),  # 2 x 2 at the top face's corner
            "skull": _square(ij, 10, 12, 4, 8)}  # fixed, two columns right of the patch
    mesh = mesh.with_node_sets(**sets)
    return mesh, top, ij


def test_a_ring_out_and_a_ring_in_on_a_known_surface(box) -> None:
    mesh, top, ij = box
    rings = AttachmentRings(mesh, ["patch", "corner"], fixed=["skull"], surface_nodes=top)
    grown = rings.sets_at({"patch": 1})["patch"]
    # a 7 x 7 square less the two corners the diagonal does not reach: (3, 9) and (9, 3)
    want = np.setdiff1d(_square(ij, 3, 9, 3, 9), [ij[(3, 9)], ij[(9, 3)]])
    assert np.array_equal(grown, want)
    assert len(grown) - 25 == 22
    shrunk = rings.sets_at({"patch": -1})["patch"]
    assert np.array_equal(shrunk, _square(ij, 5, 7, 5, 7))  # the boundary ring of 16 nodes went
    assert np.array_equal(rings.boundary(rings.original["patch"]), np.setdiff1d(rings.original["patch"], shrunk))
    # the ring stays on the top face: the corner set grows over the top only, never down the box's sides
    corner = rings.sets_at({"corner": 1})["corner"]
    assert set(corner.tolist()) <= set(top.tolist())
    assert np.array_equal(corner, _square(ij, 0, 2, 0, 2))


def test_no_node_in_two_sets_and_the_fixed_set_is_never_taken(box) -> None:
    mesh, top, ij = box
    rings = AttachmentRings(mesh, ["patch", "corner"], fixed=["skull"], surface_nodes=top)
    sets = rings.sets_at({"patch": 2, "corner": 3})
    skull = set(np.asarray(mesh.node_sets["skull"]).tolist())
    assert not set(sets["patch"].tolist()) & set(sets["corner"].tolist())
    assert not set(sets["patch"].tolist()) & skull and not set(sets["corner"].tolist()) & skull
    # two rings out reach column 10 but the skull holds it: the patch stops at column 9 there
    assert ij[(10, 6)] not in sets["patch"] and ij[(9, 6)] in sets["patch"]
    # ring by ring: the patch took (3, 3) in the first ring, so the corner set's third ring goes round it
    assert ij[(3, 3)] in sets["patch"] and ij[(3, 2)] in sets["corner"]
    assert set(rings.original["patch"].tolist()) <= set(sets["patch"].tolist())
    m = rings.mesh_at({"patch": 1})
    assert np.array_equal(np.asarray(m.nodes), np.asarray(mesh.nodes)) and m.n_tets == mesh.n_tets
    assert len(m.node_sets["patch"]) == 47 and len(m.node_sets["skull"]) == 15


def test_a_shrink_below_the_minimum_grip_is_refused_and_not_offered(box) -> None:
    mesh, top, _ = box
    rings = AttachmentRings(mesh, ["patch", "corner"], fixed=["skull"], surface_nodes=top)
    assert min_nodes(25) == 9 and min_nodes(4) == 6
    with pytest.raises(ValueError, match="minimum grip"):
        rings.sets_at({"patch": -2})  # 25 -> 9 -> 1
    cands = {(c.name, c.step): c for c in rings.candidates({"patch": -1}, {"patch": 2, "corner": 1})}
    assert not cands[("patch", -1)].allowed and "minimum grip" in cands[("patch", -1)].why
    up = cands[("patch", 1)]
    assert up.allowed and (up.nodes_before, up.nodes_after) == (9, 25)
    assert not cands[("corner", -1)].allowed  # 4 nodes: already below the minimum of 6
    assert cands[("corner", 1)].allowed and cands[("corner", 1)].nodes_after == 9
    at_limit = {(c.name, c.step): c for c in rings.candidates({"corner": 1}, {"corner": 1})}
    assert "allows 1 ring" in at_limit[("corner", 1)].why and at_limit[("corner", -1)].allowed
