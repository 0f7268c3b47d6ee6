"""The safety filter: whatever the input, commands stay inside position, velocity and acceleration limits."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from models.headspec import load_head
from runtime.safety import SafetyFilter

HEAD = load_head(Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml")
N = len(HEAD.actuators)


def test_reaches_target_smoothly_and_stops() -> None:
    sf = SafetyFilter(HEAD)
    jaw = sf.index["jaw"]
    target = sf.vector({"jaw": math.radians(20)})
    dt = 0.004
    v_prev = 0.0
    for _ in range(400):
        q_prev = sf.q[jaw]
        sf.step(target, dt)
        v = (sf.q[jaw] - q_prev) / dt
        assert abs(v) <= sf.vmax[jaw] + 1e-9
        assert abs(v - v_prev) <= sf.amax[jaw] * dt + 1e-6
        v_prev = v
    assert abs(sf.q[jaw] - math.radians(20)) < 1e-6
    assert abs(sf.v[jaw]) < 1e-6


def test_groups_and_limits() -> None:
    sf = SafetyFilter(HEAD)
    x = sf.constrain(sf.vector({"lid_l": math.radians(30), "lid_r": math.radians(10),
                                "lip_corner_l_up": math.radians(40), "lip_corner_l_back": math.radians(-30),
                                "jaw": math.radians(500)}))
    i = sf.index
    assert x[i["lid_l"]] == x[i["lid_r"]] == math.radians(20)  # "together": both lids move as one
    assert abs(x[i["lip_corner_l_up"]] - x[i["lip_corner_l_back"]]) <= math.radians(45) + 1e-12
    assert x[i["jaw"]] == HEAD.actuator("jaw").max


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.just(float("nan"))),
                         min_size=N, max_size=N), min_size=1, max_size=30),
       st.floats(min_value=1e-4, max_value=0.05), st.floats(min_value=0.01, max_value=1.0))
def test_any_input_stays_within_limits_and_rates(targets: list[list[float]], dt: float, speed: float) -> None:
    sf = SafetyFilter(HEAD)
    for row in targets:
        q_prev = sf.q.copy()
        with np.errstate(all="ignore"):
            q = sf.step(np.array(row), dt, speed)
        assert np.all(np.isfinite(q))
        assert np.all(q >= sf.lo) and np.all(q <= sf.hi)
        assert np.all(np.abs(q - q_prev) <= sf.vmax * speed * dt + 1e-9)


def test_mirror_group_keeps_members_opposite() -> None:
    import tomllib

    from models.headspec import head_from_dict

    data = tomllib.loads((Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml").read_text())
    data["groups"]["brows"] = {"kind": "mirror", "actuators": ["brow_l", "brow_r"]}
    sf = SafetyFilter(head_from_dict(data, "mirror.toml"))
    i = sf.index
    x = sf.constrain(sf.vector({"brow_l": math.radians(10), "brow_r": math.radians(-6)}))
    assert abs(x[i["brow_l"]] - math.radians(8)) < 1e-12  # the mean of 10 and -(-6)
    assert abs(x[i["brow_r"]] + x[i["brow_l"]]) < 1e-12
