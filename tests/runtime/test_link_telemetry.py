"""The daemon loads the head's link map m(p) and publishes predicted link poses at the measured actuator values."""

from __future__ import annotations

import math

import numpy as np

from models.client import Client, Telemetry
from models.headspec import load_head
from sim_hardware.mechanism import sample_mechanism
from tests._wait import wait_until
from tests.runtime.conftest import SAMPLE


def test_state_telemetry_carries_link_poses_that_match_the_mechanism(make_daemon) -> None:
    d = make_daemon()
    assert d.head.path("linkmap") is not None and d.head.path("linkmap").is_file()
    goal = {"jaw": 5.0, "cheek_l": 15.0, "lip_corner_l_up": 20.0}  # within the skin guard's range
    with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint, topics=(b"state",)) as tel:
        c.call("enable")
        c.call("pose", pose=goal, speed=1.0)

        def arrived() -> bool:
            measured = c.call("status")["measured"]
            return all(abs(measured[n] - v) < 0.2 for n, v in goal.items())

        wait_until(arrived, 30, lambda: f"every goal within 0.2; measured {c.call('status')['measured']}")
        hit = tel.wait_for(lambda topic, msg: "links" in msg and abs(msg["measured"]["jaw"] - goal["jaw"]) < 0.3, 30)
        assert hit is not None, "no state message with link poses"
        state = hit[1]
        c.call("disable")
    # Ground truth: the sample mechanism the shipped map was calibrated on, at the measured actuator values.
    head = load_head(SAMPLE)
    measured_si = {n: head.actuator(n).from_config_units(v) for n, v in state["measured"].items()}
    truth = sample_mechanism(head).link_poses(measured_si)
    assert set(state["links"]) == {link.name for link in head.links}
    for name in ("jaw", "cheek_l", "lip_corner_l", "brow_l", "skull"):
        pose = np.asarray(state["links"][name])
        assert np.linalg.norm(pose[:3] - truth[name][:3, 3]) < 0.5e-3, name  # metres
    # The jaw really moved: its predicted pose is millimetres from neutral.
    rest = sample_mechanism(head).link_poses({n: 0.0 for n in head.actuator_names})
    moved = np.linalg.norm(np.asarray(state["links"]["jaw"][:3]) - rest["jaw"][:3, 3])
    assert moved > 1e-3 and math.isfinite(moved)
