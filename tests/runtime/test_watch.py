"""The feedback watch stepped in the core, with no threads or sleeps: a bus whose devices stop reporting publishes
``feedback_late`` within its limit and then faults the head naming the bus; an actuator that stops following faults
it naming the actuator; a clip on ideal and on lagging buses raises neither. Also the limits' defaults and checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.clip import clip_from_dict
from models.errors import ConfigError
from models.headspec import head_from_dict, load_head
from runtime.config import daemon_config
from runtime.core import commands as C
from runtime.core.clips import bind_clip
from runtime.core.cycle import BusInput
from runtime.core.lifecycle import Lifecycle
from runtime.core.watch import FOLLOWING_ERROR_TIME_S, LATE_PERIODS, WatchParams, following_errors
from tests.runtime.test_core import CLIP, HEAD, SAMPLE, Rig

SWEEP = {"name": "sweep", "channels": {
    "jaw": {"interp": "linear", "keys": [[0, 0], [0.4, 25], [0.8, 0], [1.2, 25], [1.6, 0]]},
    "lip_corner_l_up": {"interp": "linear", "keys": [[0, 0], [0.5, 35], [1.0, -25], [1.6, 0]]},
    "blink": {"interp": "step", "keys": [[0, 0], [0.3, 30], [0.9, 0], [1.3, 30]]},
    "brow_l": {"interp": "linear", "keys": [[0, 0], [0.8, 15], [1.6, 0]]},
}}

HOLD = {"name": "hold", "channels": {"jaw": {"interp": "linear", "keys": [[0, 0], [0.3, 25], [1.6, 25]]}}}


def _events(rig: Rig, kind: str) -> list[dict]:
    return [e for o in rig.outputs for e in o.events if e["event"] == kind]


def _play(rig: Rig, spec: dict) -> None:
    clip = bind_clip(clip_from_dict(spec), rig.channels)
    rig.call(C.LoadClip, clip=clip, key_count=clip.key_count, nbytes=clip.nbytes)
    rig.call(C.Play, name=spec["name"])


def test_defaults_follow_the_period_and_the_safety_timeout() -> None:
    data = _head()
    for bus in data["buses"].values():
        bus.pop("feedback_timeout_s", None)
    head = head_from_dict(data, source=SAMPLE)
    cfg = daemon_config(head, {"runtime.rate_hz": 250.0})
    wp = WatchParams.build(head, cfg, tuple(head.buses), 1 / 250.0)
    assert np.allclose(wp.late_s, LATE_PERIODS / 250.0)
    assert np.allclose(wp.fault_s, cfg.safety.feedback_timeout_s)
    jaw = head.actuator("jaw")
    assert wp.max_error[0] == pytest.approx(jaw.max_velocity * 0.1)
    assert np.allclose(wp.error_time_s, FOLLOWING_ERROR_TIME_S)
    assert np.allclose(Rig().params.watch.late_s, 0.1)  # the sample head sets its emulated buses' limit


def test_silent_bus_publishes_late_then_faults_naming_it() -> None:
    rig = Rig()
    rig.call(C.Enable)
    rig.run(0.1)
    stale = rig.t
    rig.bus_inputs = lambda: tuple(BusInput(b, rig.bus_state[b], True, rig.q[idx].copy(),  # type: ignore[method-assign]
                                            stale if b == "can0" else rig.t) for b, idx in rig.params.buses)
    wp = rig.params.watch
    late_s, fault_s = float(wp.late_s[0]), float(wp.fault_s[0])
    while rig.state.lifecycle is Lifecycle.ACTIVE and rig.t - stale < 2 * fault_s:
        rig.cycle()
    late = _events(rig, "feedback_late")
    assert late and late[0]["bus"] == "can0" and late[0]["state"] == "late"
    assert late_s < late[0]["age"] <= late_s + 1.5 * rig.params.period
    assert late[0]["t"] - stale == pytest.approx(late[0]["age"])
    fault = rig.state.life.fault
    assert rig.state.lifecycle is Lifecycle.FAULT and fault.source == "timeout" and fault.bus == "can0"
    assert fault.message.startswith("bus can0: no feedback from its devices for ")
    assert fault_s < fault.t - stale <= fault_s + 1.5 * rig.params.period
    assert rig.call(C.Reset) == {"lifecycle": "inactive"}


def test_late_bus_that_recovers_publishes_recovered_and_stays_active() -> None:
    rig = Rig()
    rig.call(C.Enable)
    stale = rig.t
    rig.bus_inputs = lambda: tuple(BusInput(b, rig.bus_state[b], True, rig.q[idx].copy(),  # type: ignore[method-assign]
                                            stale if b == "dxl" else rig.t) for b, idx in rig.params.buses)
    rig.run(0.2)
    rig.bus_inputs = lambda: tuple(BusInput(b, rig.bus_state[b], True, rig.q[idx].copy(),  # type: ignore[method-assign]
                                            rig.t) for b, idx in rig.params.buses)
    rig.run(0.4)
    assert [e["state"] for e in _events(rig, "feedback_late")] == ["late"]
    rig.run(0.2)
    states = [(e["bus"], e["state"]) for e in _events(rig, "feedback_late")]
    assert states == [("dxl", "late"), ("dxl", "recovered")]
    assert _events(rig, "feedback_late")[1]["age"] >= 0.19
    assert rig.state.lifecycle is Lifecycle.ACTIVE


def test_actuator_that_stops_following_faults_naming_it() -> None:
    rig = Rig()
    rig.call(C.Enable)
    jaw = HEAD.actuator_names.index("jaw")
    stuck = rig.q[jaw]
    real = rig.bus_inputs

    def stuck_jaw() -> tuple[BusInput, ...]:
        inputs = real()
        can0 = inputs[0]
        positions = can0.positions.copy()
        positions[list(rig.params.buses[0][1]).index(jaw)] = stuck
        return (BusInput(can0.name, can0.state, True, positions, can0.stamp), *inputs[1:])

    rig.bus_inputs = stuck_jaw  # type: ignore[method-assign]
    _play(rig, HOLD)
    rig.run(1.0)
    fault = rig.state.life.fault
    assert rig.state.lifecycle is Lifecycle.FAULT and fault is not None, "no fault from a stuck jaw"
    assert fault.source == "following_error" and fault.actuator == "jaw" and fault.bus == "can0"
    assert fault.message.startswith("actuator jaw: following error ")
    assert fault.info()["actuator"] == "jaw"
    assert [e["actuator"] for e in _events(rig, "fault")] == ["jaw"]


@pytest.mark.parametrize("lag", [0, 2])
def test_normal_clip_raises_neither(lag: int) -> None:
    """Ideal buses, and buses that report the command of ``lag`` cycles before (the transport and the drive)."""
    rig = Rig()
    rig.call(C.Enable)
    history = [rig.q.copy()] * (lag + 1)
    real_cycle = rig.cycle

    def lagging(*cmds: C.Command, estop: str | None = None):  # type: ignore[no-untyped-def]
        history.append(rig.q.copy())
        rig.q = history[-1 - lag].copy()
        out = real_cycle(*cmds, estop=estop)
        return out

    rig.cycle = lagging  # type: ignore[method-assign]
    for spec in (CLIP, SWEEP):
        _play(rig, spec)
        rig.run(1.8)
    assert rig.state.lifecycle is Lifecycle.ACTIVE, rig.state.life.fault
    assert not _events(rig, "feedback_late") and not _events(rig, "fault")
    assert float(rig.state.watch.peak_error.max()) < float(rig.params.watch.max_error.min())


def test_following_error_is_the_distance_outside_the_recent_commands() -> None:
    posted = np.array([[0.0, 1.0, np.nan], [0.2, 1.0, np.nan], [0.4, 0.5, np.nan]])
    measured = np.array([0.1, 2.0, 3.0])
    assert following_errors(posted, measured).tolist() == pytest.approx([0.0, 1.0, 0.0])


def _head(bus: dict | None = None, actuator: dict | None = None) -> dict:
    import tomllib

    data = tomllib.loads(SAMPLE.read_text())
    data["buses"]["can0"].update(bus or {})
    data["actuators"][0].update(actuator or {})
    return data


@pytest.mark.parametrize(("bus", "actuator", "key", "text"), [
    ({"feedback_timeout_s": -0.1}, None, "buses.can0.feedback_timeout_s", "must be positive"),
    ({"feedback_fault_s": 0.0}, None, "buses.can0.feedback_fault_s", "must be positive"),
    ({"feedback_timeout_s": 0.2, "feedback_fault_s": 0.1}, None, "buses.can0.feedback_fault_s",
     "must be longer than feedback_timeout_s"),
    ({"feedback_timeout_s": "fast"}, None, "buses.can0.feedback_timeout_s", "expected"),
    ({"feedback_age_s": 0.1}, None, "buses.can0.feedback_age_s", "unknown key"),
    (None, {"max_following_error": -2.0}, "actuators[0] (jaw).max_following_error", "must be positive"),
    (None, {"following_error_time_s": math.inf}, "actuators[0] (jaw).following_error_time_s", "finite"),
])
def test_bad_limits_are_refused_naming_file_key_and_value(bus, actuator, key, text) -> None:
    from models.errors import SpecError

    with pytest.raises(SpecError) as info:
        head_from_dict(_head(bus, actuator), source=SAMPLE)
    message = str(info.value)
    assert str(SAMPLE) in message and key in message and text in message, message


def test_limits_in_config_units_and_against_the_loop() -> None:
    head = head_from_dict(_head({"feedback_timeout_s": 0.05, "feedback_fault_s": 0.3},
                                {"max_following_error": 4.0, "following_error_time_s": 0.1}), source=SAMPLE)
    cfg = daemon_config(head, {"runtime.rate_hz": 250.0})
    wp = WatchParams.build(head, cfg, tuple(head.buses), 1 / 250.0)
    assert wp.late_s[0] == 0.05 and wp.fault_s[0] == 0.3
    assert wp.max_error[0] == pytest.approx(math.radians(4.0)) and wp.error_time_s[0] == 0.1
    slow = head_from_dict(_head({"feedback_timeout_s": 0.9}), source=SAMPLE)
    with pytest.raises(ConfigError, match=r"buses\.can0\.feedback_timeout_s = 0\.9: must be shorter than"):
        WatchParams.build(slow, daemon_config(slow, {"safety.feedback_timeout_s": 0.5}), tuple(slow.buses), 0.004)
    fast = head_from_dict(_head({"feedback_timeout_s": 0.002, "feedback_fault_s": 0.005}), source=SAMPLE)
    with pytest.raises(ConfigError, match=r"buses\.can0\.feedback_fault_s = 0\.005: must exceed two loop periods"):
        WatchParams.build(fast, daemon_config(fast, {}), tuple(fast.buses), 0.004)


def test_the_sample_head_loads() -> None:
    assert load_head(SAMPLE).buses["can0"].driver == "canopen402"
