"""The coarse sample skin shipped in heads/sample/skin: loads, matches its report, valid sets and face units."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from offline.fem import boundary_faces, load_mesh, tet_quality
from offline.mesh.surface import closed_manifold_problems, closest_points, euler_characteristic
from offline.mesh.tetra import signed_volumes

ROOT = Path(__file__).resolve().parents[3]
SKIN = ROOT / "heads" / "sample" / "skin"


@pytest.fixture(scope="module")
def shipped():
    mesh = load_mesh(SKIN / "skin.vtu")
    report = json.loads((SKIN / "mesh_report.json").read_text())
    with np.load(SKIN / "face_units.npz") as z:
        units = {k: z[k] for k in z.files}
    return mesh, report, units


def test_files_are_small_enough_to_ship() -> None:
    total = sum(p.stat().st_size for p in SKIN.iterdir())
    assert total < 3 * 1024 * 1024


def test_mesh_matches_its_report(shipped) -> None:
    mesh, report, units = shipped
    c = report["counts"]
    assert (mesh.n_nodes, mesh.n_tets) == (c["nodes"], c["tets"])
    assert len(units["surface_nodes"]) == c["surface_nodes"]
    assert len(units["surface_triangles"]) == c["surface_triangles"]
    assert {k: len(v) for k, v in mesh.node_sets.items()} == report["node_sets"]
    q = tet_quality(mesh)
    assert q.min() == pytest.approx(report["quality"]["radius_ratio_min"], rel=1e-9)
    assert signed_volumes(mesh.nodes, mesh.tets).sum() == pytest.approx(report["volume_m3"], rel=1e-9)
    assert 1000 < mesh.n_tets < 10000  # the coarse preset: a few thousand tets


def test_tets_positive_and_boundary_watertight(shipped) -> None:
    mesh, report, _ = shipped
    assert (signed_volumes(mesh.nodes, mesh.tets) > 0).all()
    faces = boundary_faces(mesh)
    assert closed_manifold_problems(faces) == []
    assert euler_characteristic(faces) == 2 - 2 * 3  # skin with mouth and two eye openings: genus 3
    assert len(report["shell"]["boundary_loops"]) == 4
    # the shell is a skin a few millimetres thick
    t = report["thickness_mesh_m"]
    assert 0.004 < t["median"] < 0.007 and t["min"] > 0.001


def test_node_sets_named_after_head_links_disjoint_on_inner_surface(shipped) -> None:
    mesh, _, units = shipped
    head = load_head(ROOT / "heads" / "sample" / "head.toml")
    assert set(mesh.node_sets) == {link.node_set for link in head.links}
    inner = set(units["inner_nodes"].tolist())
    outer_nodes = units["surface_nodes"]
    seen: set[int] = set()
    for name, idx in mesh.node_sets.items():
        assert len(idx) > 0, name
        assert np.all(np.diff(idx) > 0), name
        assert set(idx.tolist()) <= inner, name
        assert not (seen & set(idx.tolist())), f"{name} overlaps another set"
        seen |= set(idx.tolist())
    # inner-surface nodes lie a skin thickness under the outer surface
    surf_t = units["surface_triangles"]
    _, _, d = closest_points(mesh.nodes, surf_t, mesh.nodes[np.concatenate(list(mesh.node_sets.values()))])
    assert d.min() > 0.0015
    assert not (set(outer_nodes.tolist()) & inner)  # the skin surface and the attachment side never share nodes


def test_node_sets_sit_where_their_links_are(shipped) -> None:
    mesh, _, _ = shipped
    c = {k: mesh.nodes[v].mean(axis=0) for k, v in mesh.node_sets.items()}
    for side in ("brow", "cheek", "lid", "lip_corner"):
        left, right = c[f"{side}_l"], c[f"{side}_r"]
        assert left[0] > 0.01 and right[0] < -0.01, side  # +x is the face's left
        assert abs(left[1] - right[1]) < 0.01, side  # mirror images
    assert c["brow_l"][1] > c["lid_l"][1] > c["cheek_l"][1] > c["lip_corner_l"][1]
    assert c["upper_lip"][1] > c["lower_lip"][1] > c["jaw"][1]
    assert c["skull"][1] > c["lid_l"][1]


def test_face_units_on_the_skin_surface(shipped) -> None:
    mesh, _, units = shipped
    names = list(units["names"])
    assert len(names) == 52 and len(set(names)) == 52
    assert {"jawOpen", "eyeBlinkLeft", "mouthSmileRight", "tongueOut"} <= set(names)
    off = units["offsets"]
    assert off.dtype == np.float32 and off.shape == (52, len(units["surface_nodes"]), 3)
    local = units["surface_triangles_local"]
    assert np.array_equal(units["surface_nodes"][local], units["surface_triangles"])
    jaw = np.linalg.norm(off[names.index("jawOpen")], axis=1)
    assert 0.025 < jaw.max() < 0.040  # jawOpen peaks at 38.7 mm on the source mesh
    assert mesh.nodes[units["surface_nodes"][jaw.argmax()], 1] < mesh.nodes[:, 1].mean()  # the chin moves most
    blink = np.linalg.norm(off[names.index("eyeBlinkLeft")], axis=1)
    assert mesh.nodes[units["surface_nodes"][blink.argmax()], 0] > 0
