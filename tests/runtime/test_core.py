"""The control core stepped directly, with no threads, sockets or sleeps: lifecycle, sources, safety, replay.

The buses are stood in for by feedback that follows the previous command exactly (ideal motors), so every cycle is a
pure function of the inputs built here.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.clip import clip_from_dict
from models.headspec import load_head
from runtime.config import daemon_config
from runtime.core import commands as C
from runtime.core import core as K
from runtime.core.channels import ChannelMap
from runtime.core.clips import bind_clip
from runtime.core.cycle import BusInput, CycleInputs, CycleOutputs
from runtime.core.lifecycle import Lifecycle
from runtime.core.params import CoreParams
from runtime.core.sources import Mode
from runtime.core.state import CoreState

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
HEAD = load_head(SAMPLE)
CLIP = {"name": "probe", "channels": {
    "jaw": {"interp": "linear", "keys": [[0, 0], [0.5, 15], [1.0, 15]]},
    "blink": {"interp": "step", "keys": [[0, 0], [0.3, 30]]},
    "brow_l": {"interp": "bezier", "keys": [[0, 0, 0, 0, 0.2, 0], [0.8, 12, -0.2, 0, 0, 0]]},
}}


class Rig:
    """A core on the sample head with ideal buses: each bus reports the last command as its position."""

    def __init__(self, rate_hz: float = 250.0, **overrides: object) -> None:
        self.cfg = daemon_config(HEAD, {"runtime.rate_hz": rate_hz, **overrides})
        self.channels = ChannelMap.build(HEAD)
        buses = [(b, [a.name for a in HEAD.actuators_on(b)]) for b in HEAD.buses]
        self.params = CoreParams.build(HEAD, self.cfg, self.channels, buses)
        self.state = CoreState.initial(HEAD, self.params)
        self.t = 100.0
        self.q = np.array([a.neutral for a in HEAD.actuators])
        self.bus_state = {b: "inactive" for b, _ in self.params.buses}
        self.requests: list[tuple[str, str]] = []
        self.token = 0
        self.log: list[CycleInputs] = []
        self.outputs: list[CycleOutputs] = []

    def bus_inputs(self) -> tuple[BusInput, ...]:
        return tuple(BusInput(b, self.bus_state[b], True, self.q[idx].copy(), self.t)
                     for b, idx in self.params.buses)

    def cycle(self, *cmds: C.Command, estop: str | None = None) -> CycleOutputs:
        results = tuple((b, op, True, "") for b, op in self.requests)
        for b, op in self.requests:  # ideal buses carry out every request within a cycle
            self.bus_state[b] = {"enable": "active", "disable": "inactive", "reset": "inactive"}[op]
        self.requests = []
        inputs = CycleInputs(self.t, self.bus_inputs(), cmds, results, estop)
        self.log.append(inputs)
        out = K.step(self.state, self.params, inputs)
        self.outputs.append(out)
        self.requests = list(out.bus_requests)
        if out.write is not None:
            self.q = out.write.copy()
        self.t += self.params.period
        return out

    def call(self, make: type, **fields: object) -> dict:
        """Send one command and cycle until its reply comes back (at most 50 cycles)."""
        self.token += 1
        token = self.token
        out = self.cycle(make(token, **fields))
        for _ in range(50):
            for tok, body in out.replies:
                if tok == token:
                    return body
            out = self.cycle()
        raise AssertionError(f"no reply to {make.__name__}")

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / self.params.period)):
            self.cycle()

    def deg(self, name: str) -> float:
        return math.degrees(self.q[HEAD.actuator_names.index(name)])


def test_enable_waits_for_every_bus_then_goes_active() -> None:
    rig = Rig()
    out = rig.cycle(C.Enable(1))
    assert sorted(out.bus_requests) == sorted((b, "enable") for b, _ in rig.params.buses)
    assert not out.replies and rig.state.lifecycle is Lifecycle.INACTIVE and out.write is None
    out = rig.cycle()
    assert out.replies == [(1, {"lifecycle": "active"})]
    assert rig.state.lifecycle is Lifecycle.ACTIVE


def test_clip_plays_through_groups_and_limits() -> None:
    rig = Rig()
    rig.call(C.Enable)
    clip = bind_clip(clip_from_dict(CLIP), rig.channels)
    assert rig.call(C.LoadClip, clip=clip, key_count=clip.key_count, nbytes=clip.nbytes)["duration"] == 1.0
    rig.call(C.Play, name="probe")
    rig.run(1.5)
    assert rig.deg("jaw") == pytest.approx(15.0, abs=1e-6)
    assert rig.deg("lid_l") == pytest.approx(30.0, abs=1e-6) and rig.deg("lid_r") == pytest.approx(30.0, abs=1e-6)
    assert rig.deg("brow_l") == pytest.approx(12.0, abs=1e-6)
    events = [e for o in rig.outputs for e in o.events if e["event"] == "clip"]
    assert [e["state"] for e in events] == ["playing", "finished"]


def test_every_command_stays_within_limits_and_rates() -> None:
    rig = Rig(rate_hz=500.0)
    rig.call(C.Enable)
    rng = np.random.default_rng(3)
    names = list(rig.channels.names[:rig.channels.target_start])
    lo = np.array([a.min for a in HEAD.actuators])
    hi = np.array([a.max for a in HEAD.actuators])
    vmax = np.array([a.max_velocity for a in HEAD.actuators])
    prev = rig.q.copy()
    for k in range(400):
        if k % 20 == 0:  # wild poses, far outside the limits
            chans = rng.choice(len(names), size=4, replace=False)
            rig.cycle(C.Pose(1000 + k, chans, rng.uniform(-500, 500, size=4), 1.0))
        else:
            rig.cycle()
        assert np.all(rig.q >= lo - 1e-12) and np.all(rig.q <= hi + 1e-12)
        assert np.all(np.abs(rig.q - prev) <= vmax * rig.params.period * 1.0000001)
        prev = rig.q.copy()


def test_estop_preempts_queued_commands_and_latches() -> None:
    rig = Rig()
    rig.call(C.Enable)
    rig.call(C.Pose, channels=np.array([0]), values=np.array([20.0]), speed=1.0)
    out = rig.cycle(C.Pose(50, np.array([0]), np.array([25.0]), 1.0), C.EStop(51, "test"))
    assert rig.state.lifecycle is Lifecycle.ESTOP and out.write is None
    replies = dict(out.replies)
    assert replies[51] == {"lifecycle": "estop"} and replies[50]["error"]["code"] == "estop"
    assert sorted(out.bus_requests) == sorted((b, "disable") for b, _ in rig.params.buses)
    assert rig.call(C.Enable)["error"]["code"] == "estop"
    assert rig.call(C.Reset) == {"lifecycle": "inactive"}
    assert rig.call(C.Enable) == {"lifecycle": "active"}


def test_out_of_band_estop_flag_acts_within_the_cycle() -> None:
    rig = Rig()
    rig.call(C.Enable)
    out = rig.cycle(estop="signal SIGUSR1")
    assert out.write is None and rig.state.life.estop_reason == "signal SIGUSR1"


def test_a_faulted_or_lost_bus_faults_the_head_and_torques_off_the_others() -> None:
    rig = Rig()
    rig.call(C.Enable)
    rig.bus_state["dxl"] = "fault"
    out = rig.cycle()
    assert rig.state.lifecycle is Lifecycle.FAULT and out.write is None
    assert rig.state.life.fault.bus == "dxl"
    assert out.bus_requests == [("can0", "disable")]
    assert [e for e in out.events if e["event"] == "fault"]
    assert rig.call(C.Reset) == {"lifecycle": "inactive"}


def test_stale_feedback_faults() -> None:
    rig = Rig()
    rig.call(C.Enable)
    stale = rig.t
    rig.run(0.1)
    rig.bus_inputs = lambda: tuple(BusInput(b, rig.bus_state[b], True, rig.q[idx].copy(),  # type: ignore[method-assign]
                                              stale if b == "can0" else rig.t) for b, idx in rig.params.buses)
    rig.run(rig.cfg.safety.feedback_timeout_s + 0.05)
    assert rig.state.lifecycle is Lifecycle.FAULT and rig.state.life.fault.source == "timeout"
    assert rig.state.life.fault.bus == "can0" and rig.state.life.fault.message.startswith("bus can0: ")


def test_stream_watchdog_holds_then_eases_to_neutral() -> None:
    rig = Rig()
    rig.call(C.Enable)
    jaw = rig.channels.index_of("jaw")
    times = rig.t + np.arange(5) * 0.02
    rig.call(C.Stream, times=times, channels=np.array([jaw]), rows=np.full((5, 1), 10.0))
    rig.run(0.2)
    assert rig.state.mode is Mode.STREAM and rig.deg("jaw") > 1.0
    # a frame far in the future does not postpone the watchdog
    rig.call(C.Stream, times=np.array([rig.t + 20.0]), channels=np.array([jaw]), rows=np.array([[10.0]]))
    rig.run(rig.cfg.safety.watchdog_neutral_s + 0.1)
    stages = [e["stage"] for o in rig.outputs for e in o.events if e["event"] == "watchdog"]
    assert stages == ["hold", "neutral"] and rig.state.mode is Mode.NEUTRAL


def test_replay_reproduces_the_commands_bit_for_bit() -> None:
    rig = Rig(rate_hz=500.0)
    rig.call(C.Enable)
    clip = bind_clip(clip_from_dict(CLIP), rig.channels)
    rig.call(C.LoadClip, clip=clip, key_count=clip.key_count, nbytes=clip.nbytes)
    rig.call(C.Play, name="probe")
    rig.run(0.4)
    rig.call(C.Pose, channels=np.array([1, 2]), values=np.array([10.0, -5.0]), speed=0.5)
    rig.run(0.3)
    rig.cycle(C.EStop(900, "x"))
    rig.call(C.Reset)
    writes = [None if o.write is None else o.write.copy() for o in rig.outputs]
    replies = [o.replies for o in rig.outputs]
    # replay the recorded inputs on a fresh core
    fresh = CoreState.initial(HEAD, rig.params)
    for k, inputs in enumerate(rig.log):
        out = K.step(fresh, rig.params, inputs)
        if writes[k] is None:
            assert out.write is None
        else:
            assert out.write is not None and out.write.tobytes() == writes[k].tobytes()
        assert repr(out.replies) == repr(replies[k])


def test_clip_budget_and_unload() -> None:
    rig = Rig()
    clip = bind_clip(clip_from_dict(CLIP), rig.channels)
    rig.params = replace(rig.params, cfg=daemon_config(HEAD, {"runtime.clip_memory_bytes": 65536}))
    big = replace(clip, nbytes=70000)
    assert rig.call(C.LoadClip, clip=big, key_count=1, nbytes=big.nbytes)["error"]["code"] == "too_large"
    assert rig.call(C.LoadClip, clip=clip, key_count=1, nbytes=clip.nbytes)["clip"] == "probe"
    assert rig.state.sources.clip_bytes == clip.nbytes
    assert rig.call(C.UnloadClip, name="probe")["clips"] == []
    assert rig.state.sources.clip_bytes == 0
    assert rig.call(C.UnloadClip, name="probe")["error"]["code"] == "not_found"


class _Counting:
    """A target solver that counts its resets (the solver interface in its array form)."""

    def __init__(self) -> None:
        self.resets = 0

    def channels(self) -> dict[str, str]:
        return {"expr.open": "weight"}

    def solve_array(self, block: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, dict]:
        out = np.full(len(q), np.nan)
        out[0] = math.radians(5.0) * float(block[0])
        return out, {"warm": self.resets}

    def reset_array(self, q: np.ndarray) -> None:
        self.resets += 1


def test_target_solvers_declare_channels_and_are_reset_on_fault_estop_and_reset() -> None:
    solver = _Counting()
    rig = Rig()
    rig.channels = ChannelMap.build(HEAD, [solver.channels()])
    buses = [(b, [a.name for a in HEAD.actuators_on(b)]) for b in HEAD.buses]
    rig.params = CoreParams.build(HEAD, rig.cfg, rig.channels, buses)
    rig.state = CoreState.initial(HEAD, rig.params, [solver])
    assert rig.channels.kind("expr.open") == "target"
    rig.call(C.Enable)
    after_enable = solver.resets
    assert after_enable >= 1
    k = rig.channels.index_of("expr.open")
    rig.call(C.Pose, channels=np.array([k]), values=np.array([1.0]), speed=1.0)
    rig.cycle(C.EStop(70, "x"))
    assert solver.resets > after_enable
    n = solver.resets
    rig.call(C.Reset)
    assert solver.resets > n
    rig.call(C.Enable)
    n = solver.resets
    rig.bus_state["can0"] = "fault"
    rig.cycle()
    assert rig.state.lifecycle is Lifecycle.FAULT and solver.resets > n


def test_a_new_pose_is_not_reported_settled_on_the_previous_poses_guard_verdict() -> None:
    """The strain guard stops a wide jaw opening short; the next pose starts a new judgement: a status taken as it
    arrives must not call it settled (the head has not moved yet) because the previous one was limited."""
    from models.strain_guard import StrainGuard

    rig = Rig()
    rig.params = replace(rig.params, guard=StrainGuard.for_head(HEAD))
    rig.call(C.Enable)
    jaw = np.array([rig.channels.names.index("jaw")])
    rig.cycle(C.Pose(900, jaw, np.array([28.0]), 1.0))
    rig.run(2.0)
    st = rig.call(C.Status)
    assert st["pose_settled"] and not st["pose_reached"] and st["guard"]["verdict"] != "ok"
    held = rig.deg("jaw")
    assert 1.0 < held < 27.0  # the sample skin cannot take the full opening: limited on the way
    out = rig.cycle(C.Pose(901, jaw, np.array([0.0]), 1.0), C.Status(902))
    (st,) = [body for tok, body in out.replies if tok == 902]
    assert not st["pose_settled"] and not st["pose_reached"]
    rig.run(2.0)
    st = rig.call(C.Status)
    assert st["pose_settled"] and st["pose_reached"] and abs(rig.deg("jaw")) < 1e-6


def test_every_command_kind_is_dispatched() -> None:
    """Each kind in the command union reaches a handler: refused for its own reason at worst, never an internal
    error."""
    from typing import get_args

    rig = Rig()
    clip = bind_clip(clip_from_dict(CLIP), rig.channels)
    cmds = [C.LoadClip(k, clip) if kind is C.LoadClip else kind(k) for k, kind in enumerate(get_args(C.Command))]
    out = rig.cycle(*cmds)
    codes = {tok: body["error"]["code"] for tok, body in out.replies if "error" in body}
    assert "internal" not in codes.values(), codes


def test_enable_commands_from_the_positions_the_buses_hold() -> None:
    """The drivers hold each motor where they read it while enabling and measure the first target's step against
    that; feedback measured a few milliseconds later may have moved on (a motor settling or still coasting). The
    first commands start from the held positions, so the drivers never see that motion as a step too fast to take
    (their guard refused the jaw for it, a step over a 1 ms gap between write stamps)."""
    rig = Rig(rate_hz=500.0)
    jaw = HEAD.actuator_names.index("jaw")
    held = rig.q.copy()
    held[jaw] = math.radians(10.0)
    drift = math.radians(1.5)  # measured positions ahead of the hold

    def inputs() -> tuple[BusInput, ...]:
        out = []
        for b, idx in rig.params.buses:
            measured = held[idx] + np.where(idx == jaw, drift, 0.0)
            written = held[idx].copy() if rig.bus_state[b] == "active" else None
            out.append(BusInput(b, rig.bus_state[b], True, measured, rig.t, written=written))
        return tuple(out)

    rig.bus_inputs = inputs  # type: ignore[method-assign]
    rig.call(C.Enable)
    assert rig.state.lifecycle is Lifecycle.ACTIVE
    first = next(o.write for o in rig.outputs if o.write is not None)
    assert first[jaw] == pytest.approx(held[jaw], abs=1e-12)
    # without a hold reported (an older bus process, a fake bus), the measured positions are where it starts
    rig2 = Rig(rate_hz=500.0)
    rig2.q[jaw] = math.radians(4.0)
    rig2.call(C.Enable)
    first = next(o.write for o in rig2.outputs if o.write is not None)
    assert first[jaw] == pytest.approx(math.radians(4.0), abs=1e-12)


def test_a_quiet_live_packet_is_answered_only_when_refused() -> None:
    rig = Rig()
    jaw = rig.channels.index_of("jaw")

    def live(token: int) -> C.Live:
        return C.Live(token, "osc", np.array([jaw]), np.array([6.0]), quiet=True)

    refused = rig.cycle(live(7))  # the head is not active: refused, and the refusal names the packet's token
    assert [(tok, body["error"]["code"]) for tok, body in refused.replies] == [(7, "bad_state")]
    rig.call(C.Enable)
    accepted = rig.cycle(live(7))  # taken: nobody waits for an answer, so none is sent
    assert accepted.replies == []
    rig.run(0.3)
    assert rig.state.mode is Mode.LIVE and rig.deg("jaw") > 1.0
    loud = rig.cycle(C.Live(8, "osc", np.array([jaw]), np.array([6.0])))  # a client's live values are answered
    assert [tok for tok, _ in loud.replies] == [8]
