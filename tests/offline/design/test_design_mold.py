"""Mold export on a small curved skin, and the solid checker against meshes that are not printable solids."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from offline.design.mesh_check import check_solid, check_stl
from offline.design.mold import build_mold, export_mold, skin_surfaces, volume_balance
from offline.fem import TetMesh, box_mesh, save_mesh

ROOT = Path(__file__).resolve().parents[3]


def _curved_skin() -> TetMesh:
    """A 40 × 30 × 5 mm slab bent into a dome (outer = z1 up), like a piece of face skin."""
    mesh = box_mesh((0.04, 0.03, 0.005), (6, 5, 1))
    X = np.asarray(mesh.nodes).copy()
    X[:, 2] += 0.012 * (1 - ((X[:, 0] - 0.02) / 0.025) ** 2 - ((X[:, 1] - 0.015) / 0.025) ** 2)
    return TetMesh(X, mesh.tets, dict(mesh.node_sets))


def _skin_folder(tmp: Path) -> Path:
    mesh = _curved_skin()
    folder = tmp / "skin"
    folder.mkdir()
    save_mesh(folder / "skin.vtu", mesh)
    np.savez(folder / "face_units.npz", surface_nodes=np.asarray(mesh.node_sets["z1"]),
             inner_nodes=np.asarray(mesh.node_sets["z0"]))
    return folder


def test_mold_parts_are_clean_solids_whose_cavity_less_core_is_the_skin(tmp_path):
    folder = _skin_folder(tmp_path)
    report = export_mold(folder, tmp_path / "mold")
    for name in ("skin", "mold_core", "mold_shell_left", "mold_shell_right"):
        c = check_stl(tmp_path / "mold" / f"{name}.stl")
        assert c.ok, (name, c)
        assert report["checks"][name]["ok"]
    skin_mm3 = report["checks"]["skin"]["volume"]
    assert skin_mm3 == pytest.approx(40 * 30 * 5, rel=0.02)  # millimetres; the dome bends, barely stretches
    vb = report["volume_balance_from_files"]
    assert vb["relative_difference"] < 1e-4
    assert report["volume_balance"]["flash_mm3"] < 1e-3 * skin_mm3
    # the two halves lie on either side of the parting plane
    xm = report["frame"]["parting_plane_x_mm"]
    import trimesh

    left = trimesh.load_mesh(str(tmp_path / "mold" / "mold_shell_left.stl"))
    right = trimesh.load_mesh(str(tmp_path / "mold" / "mold_shell_right.stl"))
    pin = report["settings"]["pin_length_mm"]
    assert right.vertices[:, 0].min() >= xm - 1e-3
    beyond = left.vertices[left.vertices[:, 0] > xm + 1e-3]  # only the registration pins cross the plane
    assert len(beyond) and beyond[:, 0].max() <= xm + pin + 1e-3
    assert np.all(np.abs(beyond[:, 2] - report["frame"]["box_mm"][1][2] / 2) <= report["settings"]["pin_radius_mm"]
                  + 1e-3)
    from offline.design.mold import _manifold

    # the pins sit in their sockets with clearance: the halves do not interfere
    assert (_manifold(left.vertices, left.faces) ^ _manifold(right.vertices, right.faces)).volume() < 1e-6
    assert report["volume_balance"]["pin_gap_mm3"] > 0
    assert json.loads((tmp_path / "mold" / "mold_report.json").read_text())["units"] == "mm"


def test_volume_identity_holds_before_writing():
    mesh = _curved_skin()
    sf, of, inf = skin_surfaces(mesh, np.asarray(mesh.node_sets["z1"]), np.asarray(mesh.node_sets["z0"]))
    result = build_mold(np.asarray(mesh.nodes), sf, of, inf)
    flash = result["flash_mm3"]
    assert flash == pytest.approx(sum(result["notched_mm3"].values()) + sum(result["islands_mm3"].values()))
    # exact booleans; the clean-up at 0.01 mm tolerance moves the channel walls by a few thousandths of a mm³
    assert volume_balance(result["volumes"], flash)["relative_difference"] < 1e-6
    for name, (v, f) in result["parts"].items():
        assert check_solid(v, f).ok, name


def test_pour_hole_and_vents_open_into_the_cavity_at_its_high_points():
    """The pour hole sits at the skin's highest point, vents at other local maxima; each channel reaches the skin's
    outer surface from the top of the shell, and the channels are cut from the shell (their volume is reported)."""
    from manifold3d import Manifold

    from offline.design.mold import MoldSettings, _manifold, high_points

    mesh = _curved_skin()
    sf, of, inf = skin_surfaces(mesh, np.asarray(mesh.node_sets["z1"]), np.asarray(mesh.node_sets["z0"]))
    result = build_mold(np.asarray(mesh.nodes), sf, of, inf, MoldSettings(vents=3, vent_spacing_mm=8.0))
    ch = result["channels"]
    assert ch[0]["kind"] == "pour" and all(c["kind"] == "vent" for c in ch[1:])
    V, _ = result["surfaces"]["skin_outer_surface"]  # casting frame (mm), mesh numbering
    assert ch[0]["at_mm"][2] == pytest.approx(V[np.unique(of)][:, 2].max(), abs=1e-9)  # the dome's top
    assert result["volumes"]["channels_mm3"] > 0
    # the shell has no material along each channel's axis between the skin and the box top
    shell = _manifold(*result["parts"]["mold_shell_left"]) + _manifold(*result["parts"]["mold_shell_right"])
    z_top = result["frame"]["box_mm"][1][2]
    for c in ch:
        x, y, z = c["at_mm"]
        probe = Manifold.cylinder(z_top - z - 0.6, 0.3, 0.3, 16).translate([x, y, z + 0.3])
        assert (probe ^ shell).volume() < 1e-6, c
        assert (probe.translate([6.0, 0.0, 0.0]) ^ shell).volume() > 0  # beside the channel, the shell is there
    # a dome has one high point: with a wide spacing there is nothing else to vent
    V2 = np.asarray(mesh.nodes) * 1e3
    assert len(high_points(V2, of, 200.0, 5)) == 1


def _tet(offset) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) + offset
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def test_checker_refuses_what_is_not_a_printable_solid():
    v, f = _tet(0.0)
    good = check_solid(v, f)
    assert good.ok and good.volume == pytest.approx(1 / 6)
    assert not check_solid(v, f[:3]).watertight  # a face missing
    flipped = check_solid(v, f[:, ::-1])
    assert flipped.consistently_oriented and not flipped.outward
    mixed = f.copy()
    mixed[0] = mixed[0, ::-1]
    assert not check_solid(v, mixed).consistently_oriented
    v2, f2 = _tet(np.array([0.2, 0.2, 0.2]))  # a second tetrahedron poking through the first
    both = check_solid(np.vstack([v, v2]), np.vstack([f, f2 + 4]))
    assert both.watertight and both.self_intersections > 0 and not both.ok
    apart = check_solid(np.vstack([v, v2 + 5]), np.vstack([f, f2 + 4]))
    assert apart.ok and apart.components == 2


def test_export_mold_cli_names_a_bad_skin_folder(tmp_path):
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    r = subprocess.run([sys.executable, "-m", "likeness.cli", "offline", "export-mold", "--skin",
                        str(tmp_path / "nothing"), "--out", str(tmp_path / "m")], capture_output=True, text=True,
                       env=env, cwd=ROOT)
    assert r.returncode != 0
    assert "skin.vtu" in r.stderr


def test_export_mold_refuses_a_skin_that_passes_through_itself(tmp_path):
    """A skin whose boundary crosses itself is refused before any boolean, naming the file and where."""
    from models.errors import SpecError
    from offline.fem import load_mesh

    skin = ROOT / "heads" / "sample" / "skin"
    mesh = load_mesh(skin / "skin.vtu")
    with np.load(skin / "face_units.npz") as z:
        outer, inner = np.asarray(z["surface_nodes"]), np.asarray(z["inner_nodes"])
    nodes = np.array(mesh.nodes)
    X = nodes[outer]
    k = int(inner[len(inner) // 2])
    nearest = X[np.argmin(np.linalg.norm(X - nodes[k], axis=1))]
    nodes[k] += 3.0 * (nearest - nodes[k])  # an inner node pushed out through the outer surface
    save_mesh(tmp_path / "skin.vtu", TetMesh(nodes, mesh.tets, mesh.node_sets))
    (tmp_path / "face_units.npz").write_bytes((skin / "face_units.npz").read_bytes())
    with pytest.raises(SpecError, match=r"skin\.vtu: surface: \d+ pairs of its boundary triangles cross each other"):
        export_mold(tmp_path, tmp_path / "mold")


@pytest.mark.slow
def test_the_layered_sample_skin_gets_a_clean_mold(tmp_path):
    """The two-layer design skin's finer inner surface leaves STL defects the default notches cannot clear; the
    export builds it again with the next repair settings, and every part passes its checks."""
    from offline.design.layered import layered_skin_folder

    layered_skin_folder(ROOT / "heads" / "sample" / "skin", tmp_path / "skin", layers=2)
    report = export_mold(tmp_path / "skin", tmp_path / "mold")
    assert all(c["ok"] for c in report["checks"].values())
    assert abs(report["volume_balance"]["relative_difference"]) < 1e-3
