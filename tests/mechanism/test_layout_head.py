"""The redesigned head folder: its mechanism file says what the design says, its link map agrees with it, the FEM
problem of the dataset and clone commands loads it, and the daemon runs it on emulated hardware."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.headspec import load_head
from models.mechanism import Mechanism, load_mechanism
from offline.design.mechanism_design_envelope import Envelope, design_space
from offline.design.mechanism_design_head import write_head
from offline.design.mechanism_design_kin import DesignedMechanism
from tests._wait import wait_until
from tests.runtime.conftest import SAMPLE, daemon_overrides, enable_retrying


@pytest.fixture(scope="module")
def redesigned(tmp_path_factory):
    spec = load_mechanism(load_head(SAMPLE).path("mechanism"))
    space = design_space(spec, Envelope())
    theta = np.zeros(space.size)

    def put(item: str, what: str, value) -> None:
        g = next(g for g in space.groups if g.item == item and g.what == what)
        theta[list(g.index)] = value

    put("joints.jaw_hinge", "anchor", [0.0, -0.004, 0.006])  # the hinge 7.2 mm lower and further forward
    put("couplers.jaw_rod", "length", 0.002)
    put("joints.lower_lip_guide", "axis", [math.radians(8.0), 0.0])
    put("motors.lower_lip", "ratio", 0.06)
    dm = DesignedMechanism(space, theta)
    out = tmp_path_factory.mktemp("layout") / "head"
    checks = write_head(SAMPLE, dm, out, map_samples=80, node_sets=_grown_jaw())
    return dm, out, checks


def _grown_jaw() -> dict[str, np.ndarray]:
    """The sample skin's attachment sets with the jaw's grown by one ring of inner-surface triangles."""
    from offline.design.attachment_rings import AttachmentRings
    from offline.fem.mesh import load_mesh

    skin = SAMPLE.parent / "skin"
    mesh = load_mesh(skin / "skin.vtu")
    with np.load(skin / "face_units.npz") as z:
        inner = np.asarray(z["inner_nodes"])
    links = [n for n in mesh.node_sets if n != "skull"]
    return AttachmentRings(mesh, links, fixed=["skull"], surface_nodes=inner).sets_at({"jaw": 1})


def test_the_written_mechanism_and_link_map_reproduce_the_design(redesigned) -> None:
    dm, out, checks = redesigned
    assert checks["file_vs_design_max_mm"] < 1e-3
    assert checks["map_vs_mechanism_max_mm"] < 0.05
    head = load_head(out / "head.toml")
    written = Mechanism.load(head.path("mechanism"))  # closes at neutral: load refuses a gap over 1 µm
    written.check_against(head)
    assert head.path("linkmap").parent == out and head.path("mechanism").parent == out
    # the design really changed the jaw's path: at 20 degrees the chin is elsewhere than today's
    today = Mechanism(dm.space.spec)
    values = {"jaw": math.radians(20.0)}
    moved = np.linalg.norm(written.link_poses(values)["jaw"][:3, 3] - today.link_poses(values)["jaw"][:3, 3])
    assert moved > 1e-3


def test_the_fem_problem_of_dataset_and_clone_loads_the_redesigned_head(redesigned) -> None:
    from offline.design.face import load_face

    dm, out, checks = redesigned
    face = load_face(out / "head.toml")
    head = face.skin.head
    p = np.zeros(len(head.actuator_names))
    p[head.actuator_names.index("jaw")] = math.radians(15.0)
    p[head.actuator_names.index("lower_lip")] = math.radians(20.0)
    grown = _grown_jaw()["jaw"]
    assert np.array_equal(np.sort(np.asarray(face.mesh.node_sets["jaw"])), grown)  # the skin carries the new set
    assert len(grown) > 58 and checks["skin_node_sets"]["jaw"] == len(grown)
    bc = face.space.boundary(p)  # through the head's new link map
    T = dm.transforms(dict(zip(head.actuator_names, p, strict=True)))
    X = np.asarray(face.mesh.nodes)
    for link in ("jaw", "lower_lip"):
        idx = np.asarray(face.mesh.node_sets[face.skin.moving[link]])
        want = X[idx] @ T[link][:3, :3].T + T[link][:3, 3]
        got = bc.positions[np.searchsorted(bc.nodes, idx)]
        assert np.abs(got - want).max() < 0.1e-3, link


def test_the_daemon_runs_the_redesigned_head_on_emulated_hardware(redesigned, tmp_path) -> None:
    from models.client import Client, Telemetry
    from runtime.daemon import Daemon

    dm, out, _ = redesigned
    head = load_head(out / "head.toml")
    daemon = Daemon(head, daemon_overrides(tmp_path))
    daemon.start()
    try:
        goal = {"jaw": 5.0, "lower_lip": 6.0}  # within the skin guard's range
        with Client(daemon.command_endpoint, timeout=30) as c, \
                Telemetry(daemon.telemetry_endpoint, topics=(b"state",)) as tel:
            enable_retrying(c)
            c.call("pose", pose=goal, speed=1.0)
            wait_until(lambda: all(abs(c.call("status")["measured"][n] - v) < 0.2 for n, v in goal.items()), 30,
                       "the redesigned head's jaw and lower lip reach their goals")
            hit = tel.wait_for(lambda topic, msg: "links" in msg and abs(msg["measured"]["jaw"] - 5.0) < 0.3, 30)
            assert hit is not None, "no state message with link poses"
            c.call("disable")
        state = hit[1]
        measured = {n: head.actuator(n).from_config_units(v) for n, v in state["measured"].items()}
        T = dm.transforms(measured)
        for link in ("jaw", "lower_lip"):
            want = T[link] @ dm.spec.bodies[link].rest
            assert np.linalg.norm(np.asarray(state["links"][link][:3]) - want[:3, 3]) < 0.5e-3, link
    finally:
        daemon.stop()
