"""``likeness offline simulate`` on the shipped coarse skin: links move exactly, the skull stays, Newton converges."""

from __future__ import annotations

import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from likeness.cli import main
from offline.fem import load_mesh
from offline.skin_pose import compact_transform, parse_link_spec

ROOT = Path(__file__).resolve().parents[3]
SKIN = ROOT / "heads" / "sample" / "skin"


@pytest.fixture(scope="module")
def mesh():
    return load_mesh(SKIN / "skin.vtu")


def test_compact_transform_rotates_about_centroid_then_translates() -> None:
    c = np.array([0.01, 0.6, 0.1])
    T = compact_transform(c, [1.0, 2.0, 3.0, 0.0, 0.0, 90.0])
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    assert np.allclose(T[:3, :3] @ c + T[:3, 3], c + np.array([0.001, 0.002, 0.003]))  # centroid only shifts
    p = c + np.array([0.01, 0.0, 0.0])
    assert np.allclose(T[:3, :3] @ p + T[:3, 3], c + np.array([0.001, 0.002 + 0.01, 0.003]))  # +x turns to +y about z
    assert parse_link_spec("jaw=0,0,0,5,0,0") == ("jaw", [0.0, 0.0, 0.0, 5.0, 0.0, 0.0])
    for bad in ("jaw", "jaw=1,2", "jaw=1,2,3,4,5,x", "=1,2,3,4,5,6", "jaw=1,2,3,4,5,nan"):
        with pytest.raises(ValueError, match="--link"):
            parse_link_spec(bad)


def test_jaw_rotation_converges_moves_jaw_exactly_and_keeps_skull(tmp_path, mesh, capsys) -> None:
    out = tmp_path / "deformed.vtu"
    rc = main(["offline", "simulate", "--mesh", str(SKIN), "--link", "jaw=0,0,0,4,0,0", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "converged in" in text and "residual" in text and "total" in text
    # The sample head's [skin_material]: fitted Ecoflex 00-50, nu from the head config.
    assert "material: neo_hookean, E = 62646.7 Pa, nu = 0.47 (skin_material.fit in head.toml" in text
    res = meshio.read(out)
    u = res.point_data["displacement"]
    assert np.allclose(res.points, mesh.nodes + u)
    jaw = mesh.node_sets["jaw"]
    T = compact_transform(mesh.nodes[jaw].mean(axis=0), [0, 0, 0, 4, 0, 0])
    expected = mesh.nodes[jaw] @ T[:3, :3].T + T[:3, 3]
    assert np.abs(res.points[jaw] - expected).max() < 1e-12
    assert np.linalg.norm(u[jaw], axis=1).max() > 5e-4  # 4 degrees moves the jaw patch by millimetres
    assert np.abs(u[mesh.node_sets["skull"]]).max() == 0.0
    assert np.abs(u[mesh.node_sets["brow_l"]]).max() == 0.0  # other links hold their rest pose
    constrained = np.zeros(mesh.n_nodes, dtype=bool)
    for idx in mesh.node_sets.values():
        constrained[idx] = True
    free_motion = np.linalg.norm(u[~constrained], axis=1)
    assert free_motion.max() > 1e-4  # the skin follows the jaw
    assert np.array_equal(res.point_data["set:jaw"].nonzero()[0], jaw)


def test_links_json_translation(tmp_path, mesh, capsys) -> None:
    T = np.eye(4)
    T[1, 3] = 0.001  # lift the left lid patch by 1 mm
    links = tmp_path / "links.json"
    links.write_text(json.dumps({"lid_l": T.tolist(), "brow_l": [0, 0.5, 0, 0, 0, 0]}))
    out = tmp_path / "lid.vtu"
    rc = main(["offline", "simulate", "--mesh", str(SKIN / "skin.vtu"), "--links", str(links), "--out", str(out),
               "--backend", "superlu", "--load-steps", "1"])
    assert rc == 0, capsys.readouterr().out
    u = meshio.read(out).point_data["displacement"]
    assert np.allclose(u[mesh.node_sets["lid_l"]], [0.0, 0.001, 0.0], atol=1e-12)
    assert np.allclose(u[mesh.node_sets["brow_l"]], [0.0, 0.0005, 0.0], atol=1e-12)
    assert np.abs(u[mesh.node_sets["lid_r"]]).max() == 0.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--link", "chin=0,0,0,1,0,0"], "'chin' is not a link node set"),
        (["--link", "jaw=1,2"], "expected 6 finite numbers"),
        (["--actuators", "jaw=99"], "outside [-2, 28] deg"),
        (["--actuators", "nose=3"], "'nose' is not an actuator"),
        (["--actuators", "jaw"], "expected NAME=VALUE"),
        (["--link", "jaw=0,0,0,1,0,0", "--nu", "0.5"], "--nu"),
        (["--link", "jaw=0,0,0,1,0,0", "--load-steps", "many"], "--load-steps"),
    ],
)
def test_cli_errors(tmp_path, capsys, args, message) -> None:
    rc = main(["offline", "simulate", "--mesh", str(SKIN), "--out", str(tmp_path / "x.vtu"), *args])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.vtu").exists()


def test_not_converged_exits_1_and_writes_nothing(tmp_path, capsys) -> None:
    out = tmp_path / "x.vtu"
    rc = main(["offline", "simulate", "--mesh", str(SKIN), "--link", "jaw=0,0,0,4,0,0", "--max-iterations", "1",
               "--load-steps", "1", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 1
    assert "NOT CONVERGED" in text and "state saved to" in text
    assert not out.exists()


def test_bad_links_json_and_missing_mesh(tmp_path, capsys) -> None:
    bad = tmp_path / "links.json"
    bad.write_text(json.dumps({"jaw": [[1, 0, 0], [0, 1, 0]]}))
    out = str(tmp_path / "o.vtu")
    assert main(["offline", "simulate", "--mesh", str(SKIN), "--links", str(bad), "--out", out]) == 2
    assert "key 'jaw'" in capsys.readouterr().err
    assert main(["offline", "simulate", "--mesh", str(tmp_path), "--link", "jaw=0,0,0,1,0,0",
                 "--out", str(tmp_path / "o.vtu")]) == 2
    assert "no skin.vtu" in capsys.readouterr().err


def test_actuators_through_a_link_map(tmp_path, mesh, capsys) -> None:
    from models.linkmap import LinkFit, LinkMap

    centre = mesh.nodes[mesh.node_sets["jaw"]].mean(axis=0)
    coef = np.zeros((3, 6))  # features [1, x, x^2] of the normalised jaw angle
    coef[0, :3] = centre
    coef[1, 3] = 0.1  # rotation about x: 0.1 rad per normalised unit
    coef[1, 1] = -0.002  # and 2 mm down
    lm = LinkMap(["jaw"], [0.0], [np.radians(15.0)], {"jaw": LinkFit("jaw", ("jaw",), coef, np.eye(3))})
    path = lm.save(tmp_path / "linkmap.json")
    out = tmp_path / "act.vtu"
    rc = main(["offline", "simulate", "--mesh", str(SKIN), "--actuators", "jaw=6", "--linkmap", str(path),
               "--out", str(out)])
    assert rc == 0, capsys.readouterr().out
    T = lm.transforms({"jaw": np.radians(6.0)})["jaw"]
    jaw = mesh.node_sets["jaw"]
    pts = meshio.read(out).points
    assert np.abs(pts[jaw] - (mesh.nodes[jaw] @ T[:3, :3].T + T[:3, 3])).max() < 1e-12
    assert np.abs(pts[jaw] - mesh.nodes[jaw]).max() > 1e-3
