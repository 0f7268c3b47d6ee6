"""The control core: one explicit state object and a pure ``step(state, params, inputs) -> outputs``.

A cycle runs the stages read → sources → solve → safety → write on arrays:

- **read**: the latest feedback of every bus (a snapshot the runner took without blocking) becomes the measured
  positions; bus states, disconnections and stale feedback become faults.
- **commands**: ready-made commands from the API server (e-stop first, whatever else is queued), and the outcomes of
  bus lifecycle requests (enable, disable, reset run in the bus processes, asynchronously).
- **sources**: the active source (clip, stream jitter buffer, pose, neutral, hold) gives a channel vector.
- **solve**: channel vector → actuator targets (actuator channels, groups, target solvers).
- **safety**: group constraints and limits, the skin-strain guard, and the motion shaper.
- **write**: the shaped command vector, which the runner posts to the bus processes.

The core has no threads, sockets, clocks or globals: time comes in with the inputs, so it can be stepped in tests
and replayed from a recording of its inputs, bit for bit. Lifecycle (after ros2_control): unconfigured → inactive
(buses open, torque off) → active (commanding) → fault or estop (latched) → ``reset`` → inactive.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models import errors as E
from models.headspec import HeadSpec
from models.protocol import error_body
from runtime.config import DaemonConfig
from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.core.chase import HOLD as CHASE_HOLD
from runtime.core.chase import Chase, ChaseParams
from runtime.core.live import LiveValues
from runtime.core.stream import StreamBuffer
from runtime.safety import VELOCITY_MARGIN, SafetyFilter
from runtime.shaper import Shaper
from runtime.timeline import Timeline


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FAULT = "fault"
    ESTOP = "estop"


class Mode(enum.Enum):
    HOLD = "hold"
    CLIP = "clip"
    STREAM = "stream"
    POSE = "pose"
    NEUTRAL = "neutral"
    LIVE = "live"  # values from a show-control input (OSC, sACN)


#: Bisections of the strain guard toward a refused target, per cycle.
GUARD_BISECTIONS = 3
#: After the buses answered a transition, how long their feedback may take to show the new state.
FEEDBACK_LAG_S = 1.0
#: A bus lifecycle transition that has not answered within this long fails.
TRANSITION_TIMEOUT_S = 15.0


@dataclass(frozen=True)
class BusInput:
    """One bus's latest feedback, as the runner read it (SI, this bus's actuators in order)."""

    name: str
    state: str  # drivers.base.LifecycleState value
    connected: bool
    positions: np.ndarray
    stamp: float  # when the sample was taken (monotonic)
    faults: dict[str, tuple[int, str]] = field(default_factory=dict)
    link: str = ""  # runtime.buslink.LINK_STATES ("" when the source does not say: taken from ``connected``)
    attempts: int = 0  # reconnect attempts since the connection was lost
    retry_at: float = float("inf")  # when the bus process tries to reconnect next (monotonic)


@dataclass(frozen=True)
class CycleInputs:
    """Everything a cycle depends on."""

    t: float
    buses: tuple[BusInput, ...]
    commands: tuple[C.Command, ...] = ()
    results: tuple[tuple[str, str, bool, str], ...] = ()  # (bus, op, ok, message) of finished bus requests
    estop: str | None = None  # an out-of-band e-stop (shared flag, signal): its reason
    between_cycles: bool = False  # commands taken between two cycles (no read, no write)


@dataclass
class CycleOutputs:
    """What a cycle asks the world to do."""

    write: np.ndarray | None = None  # commanded positions (SI) to post to the buses, None: write nothing
    bus_requests: list[tuple[str, str]] = field(default_factory=list)  # (bus, "enable" | "disable" | "reset")
    replies: list[tuple[int, dict[str, Any]]] = field(default_factory=list)  # (token, body or {"error": ...})
    events: list[dict[str, Any]] = field(default_factory=list)
    telemetry: dict[str, Any] | None = None
    record: np.ndarray | None = None  # rows [t, commanded..., measured...] recorded since the last output


@dataclass(frozen=True)
class CoreParams:
    """Everything fixed for a run: the head's actuators, buses, channels and the daemon settings (SI)."""

    names: tuple[str, ...]
    scale: np.ndarray  # SI per configured unit, per actuator
    period: float
    buses: tuple[tuple[str, np.ndarray], ...]  # bus name → indices of its actuators, in the bus's order
    channels: ChannelMap
    cfg: DaemonConfig
    telemetry_every: int
    record_capacity: int
    guard: Any = None  # skin-strain guard: limit(p_from, p_to) -> (p, verdict) and check(p) -> bool; None: no guard
    chase: ChaseParams | None = None  # timecode chase ([inputs.timecode]); None: no timecode input

    @classmethod
    def build(cls, head: HeadSpec, cfg: DaemonConfig, channels: ChannelMap,
              bus_order: Sequence[tuple[str, Sequence[str]]], guard: Any = None,
              chase: ChaseParams | None = None) -> CoreParams:
        index = {n: i for i, n in enumerate(head.actuator_names)}
        rt = cfg.runtime
        return cls(
            names=head.actuator_names, scale=np.array([a.unit_scale for a in head.actuators]),
            period=1.0 / rt.rate_hz,
            buses=tuple((b, np.array([index[m] for m in motors], dtype=np.intp)) for b, motors in bus_order),
            channels=channels, cfg=cfg, telemetry_every=max(1, round(rt.rate_hz / rt.telemetry_hz)),
            record_capacity=int(rt.record_max_s * rt.rate_hz) + 1, guard=guard, chase=chase,
        )


@dataclass
class Transition:
    """A lifecycle request waiting for the buses: which op, whose reply, since when, which buses still pending."""

    op: str
    token: int | None
    since: float
    pending: set[str]
    failed: list[str] = field(default_factory=list)
    requested: set[str] = field(default_factory=set)
    answered: float | None = None  # when the last bus answered

    def __post_init__(self) -> None:
        self.requested = set(self.pending)


@dataclass
class CoreState:
    """All mutable state of the control core (the daemon's only state that changes at loop rate)."""

    lifecycle: Lifecycle
    mode: Mode
    safety: SafetyFilter  # limits, groups, neutral (stateless use: constrain against the shaper's command)
    shaper: Shaper  # commanded position, velocity and acceleration (jerk-limited, ruckig)
    timeline: Timeline
    stream: StreamBuffer
    solvers: list[Any]  # target solvers (warm starts are state: reset on enable, fault, e-stop, reset)
    measured: np.ndarray
    stamps: np.ndarray  # feedback sample time per actuator
    bus_states: dict[str, str]
    bus_connected: dict[str, bool]
    bus_faults: dict[str, dict[str, tuple[int, str]]]
    channel_values: np.ndarray  # scratch: this cycle's channel vector
    bus_links: dict[str, dict[str, Any]] = field(default_factory=dict)  # connection state per bus, for telemetry
    links_reported: dict[str, str] = field(default_factory=dict)  # the connection states already announced
    pose_target: np.ndarray | None = None
    pose_speed: float = 0.25
    transition: Transition | None = None
    fault_info: dict[str, Any] | None = None
    estop_reason: str | None = None
    enabled_at: float = 0.0
    watchdog_stage: str = ""
    clip_done_reported: bool = False
    cycle: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    recording: str | None = None
    record_rows: np.ndarray | None = None
    record_count: int = 0  # rows in record_rows not yet handed out
    record_total: int = 0
    record_t0: float = 0.0
    clip_bytes: int = 0
    guard_ok: np.ndarray | None = None  # the last target the skin guard accepted
    guard_verdict: str = "ok"
    guard_refused: int = 0  # targets limited or held by the guard since start
    live: LiveValues | None = None  # latest values of the live input (OSC, sACN) in mode LIVE
    chase: Chase | None = None  # timecode chase, when a timecode input is configured
    source: str | None = None  # what drives the head: "api", "osc", "sacn", "timecode" (None: nothing)

    @classmethod
    def initial(cls, head: HeadSpec, params: CoreParams, solvers: Sequence[Any] = ()) -> CoreState:
        n = len(params.names)
        rt = params.cfg.runtime
        return cls(
            lifecycle=Lifecycle.INACTIVE, mode=Mode.HOLD, safety=SafetyFilter(head),
            shaper=_make_shaper(head, params.period), timeline=Timeline(),
            stream=StreamBuffer(params.channels.n, rt.stream_delay_s, rt.stream_max_frames, rt.stream_max_ahead_s),
            solvers=list(solvers), measured=np.full(n, np.nan), stamps=np.full(n, -np.inf),
            bus_states={b: "unconfigured" for b, _ in params.buses},
            bus_connected={b: False for b, _ in params.buses}, bus_faults={b: {} for b, _ in params.buses},
            channel_values=np.full(params.channels.n, np.nan), pose_speed=params.cfg.safety.safe_speed,
            live=LiveValues(params.channels.n), chase=None if params.chase is None else Chase(params.chase),
        )


def _make_shaper(head: HeadSpec, period: float) -> Shaper:
    shaper = Shaper.from_head(head, dt=period, velocity_margin=VELOCITY_MARGIN)
    shaper.reset(np.array([a.neutral for a in head.actuators]))
    return shaper


# ====================================================================== the step
def step(state: CoreState, params: CoreParams, inputs: CycleInputs) -> CycleOutputs:
    """Advance the core by one cycle at time ``inputs.t``; with ``inputs.between_cycles`` only take the commands
    (and e-stop) that arrived between two cycles. The only functions that change ``state``."""
    if inputs.between_cycles:
        return take_commands(state, params, inputs)
    out = CycleOutputs()
    t = inputs.t
    _read(state, params, inputs)
    _link_events(state, params, out, t)
    _commands(state, params, inputs, out)
    for result in inputs.results:
        _bus_result(state, params, out, t, *result)
    _check_transition(state, params, out, t)
    if state.lifecycle in (Lifecycle.ACTIVE, Lifecycle.INACTIVE) and state.transition is None:
        _supervise(state, params, out, t)
    if state.chase is not None:
        _chase_step(state, out, t)
    if state.lifecycle is Lifecycle.ACTIVE and state.transition is None:
        try:
            targets, speed = _sources(state, params, out, t)
            hold = np.isnan(targets)
            if params.guard is not None:  # constrains, then keeps to what the skin takes
                targets = _guard(state, params, targets)
            else:
                targets = state.safety.constrain(targets, state.shaper.q)
            out.write = _shape(state, targets, speed, hold)
        except Exception as exc:  # a failing solver or a bug: nothing is written, the head faults, replies stand
            out.write = None
            _fault(state, params, out, t, "control loop", f"control cycle failed: {type(exc).__name__}: {exc}")

    _record(state, params, out, t)
    state.cycle += 1
    if state.cycle % params.telemetry_every == 0:
        out.telemetry = _snapshot(state, params, t)
    return out


def take_commands(state: CoreState, params: CoreParams, inputs: CycleInputs) -> CycleOutputs:
    """Commands that arrived between two cycles, taken at once so their replies (and stream frames) do not wait for
    the next cycle; the bus feedback is taken in, nothing is solved or written."""
    out = CycleOutputs()
    if inputs.buses:
        _read(state, params, inputs)  # bus states as the commands find them (enable checks them)
    _commands(state, params, inputs, out)
    return out


def _commands(state: CoreState, params: CoreParams, inputs: CycleInputs, out: CycleOutputs) -> None:
    t = inputs.t
    if inputs.estop is not None:
        _estop(state, params, out, t, inputs.estop)
    cmds = inputs.commands
    if any(isinstance(c, C.EStop) for c in cmds):  # e-stop preempts whatever else is queued with it
        cmds = tuple(c for c in cmds if isinstance(c, C.EStop)) + tuple(c for c in cmds if not isinstance(c, C.EStop))
    for cmd in cmds:
        try:
            body = _HANDLERS[type(cmd)](state, params, out, t, cmd)
        except Exception as exc:  # refused (a models.errors kind: its protocol code) or a bug (internal): answered,
            out.replies.append((cmd.token, {"error": error_body(exc)}))  # and the other commands still run
        else:
            if body is not None:
                out.replies.append((cmd.token, body))


# ---------------------------------------------------------------------- read
def _read(state: CoreState, params: CoreParams, inputs: CycleInputs) -> None:
    for (name, idx), bus in zip(params.buses, inputs.buses, strict=True):
        state.measured[idx] = bus.positions
        state.stamps[idx] = bus.stamp
        state.bus_states[name] = bus.state
        state.bus_connected[name] = bus.connected
        state.bus_faults[name] = bus.faults
        link = bus.link or ("connected" if bus.connected else "closed")
        state.bus_links[name] = {"state": link, "attempts": bus.attempts,
                                 "retry_in_s": max(0.0, bus.retry_at - inputs.t) if bus.retry_at < 1e300 else None}


def _link_events(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    """A ``bus_link`` event whenever a bus's connection state changes (lost, reconnecting, connected)."""
    for name, info in state.bus_links.items():
        previous = state.links_reported.get(name)
        if info["state"] != previous:
            state.links_reported[name] = info["state"]
            if previous is not None and previous != "closed":
                _event(out, t, "bus_link", bus=name, state=info["state"], previous=previous,
                       attempts=info["attempts"], retry_in_s=info["retry_in_s"])


def _supervise(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    """Every bus connected (active and inactive heads: a lost bus faults, naming it); when active also every bus
    active and feedback fresh."""
    for name, _ in params.buses:
        lost = state.bus_links.get(name, {}).get("state") in ("lost", "reconnecting")
        if not state.bus_connected[name] and (lost or state.lifecycle is Lifecycle.ACTIVE):
            why = "; ".join(m for _, m in state.bus_faults[name].values())
            _fault(state, params, out, t, "bus", f"bus {name}: connection lost" + (f" ({why})" if why else ""),
                   bus=name)
            return
    if state.lifecycle is not Lifecycle.ACTIVE:
        for name, _ in params.buses:  # a device fault on a bus with torque off (a lost heartbeat) faults the head too
            if state.bus_states[name] == "fault":
                _fault(state, params, out, t, "driver", f"bus {name}: {_fault_detail(state, name)}", bus=name)
                return
        return
    for name, _ in params.buses:
        if state.bus_states[name] != "active":
            _fault(state, params, out, t, "driver", f"bus {name}: {_fault_detail(state, name)}", bus=name)
            return
    timeout = params.cfg.safety.feedback_timeout_s
    if t - state.enabled_at > timeout:
        age = t - state.stamps
        stale = np.flatnonzero(age > timeout)
        if stale.size:
            names = ", ".join(params.names[i] for i in stale[:6])
            buses = [b for b, idx in params.buses if np.isin(idx, stale).any()]
            where = f"bus {buses[0]}: " if len(buses) == 1 else ""
            _fault(state, params, out, t, "timeout", f"{where}no fresh feedback for {timeout:g} s from {names}",
                   bus=buses[0] if len(buses) == 1 else None)


def _fault_detail(state: CoreState, bus: str) -> str:
    faults = state.bus_faults[bus]
    return "; ".join(f"{d}: 0x{c:04X} {m}" for d, (c, m) in faults.items()) or f"bus state {state.bus_states[bus]}"


def _shape(state: CoreState, x: np.ndarray, speed: float, hold: np.ndarray) -> np.ndarray:
    """The shaper on constrained targets ``x``: an actuator told to hold (``hold``) whose constrained target is just
    its present command brakes to a stop where it is instead of being sent back there."""
    if hold.any():
        x = np.where(hold & (x == state.shaper.q), np.nan, x)
    return state.shaper.step(x, speed).copy()


def _guard(state: CoreState, params: CoreParams, targets: np.ndarray) -> np.ndarray:
    """The skin-strain guard on this cycle's target, whatever its source: a pose whose strain the skin cannot
    take is pulled back toward the last accepted one (or that one is held)."""
    x = state.safety.constrain(targets, state.shaper.q)
    if state.guard_ok is None:
        state.guard_ok = state.shaper.q.copy()
    if np.array_equal(x, state.guard_ok):
        return x
    # Three bisections: the furthest passing point within 1/8 of this cycle's (short) step; the segment between
    # two constrained poses stays constrained (groups and limits are convex), so the result needs no second pass.
    p, verdict = params.guard.limit(state.guard_ok, x, steps=GUARD_BISECTIONS)
    state.guard_ok = p
    if verdict != "ok":
        state.guard_refused += 1
    state.guard_verdict = verdict
    return p


# ---------------------------------------------------------------------- sources and solve
def _sources(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> tuple[np.ndarray, float]:
    """Actuator targets (SI, NaN = hold) and the speed fraction for this cycle, from the active source."""
    n = len(params.names)
    sf = params.cfg.safety
    mode = state.mode
    values = state.channel_values
    if mode is Mode.CLIP:
        tl = state.timeline
        ct = tl.clip_time(t)
        if ct is None:
            return np.full(n, np.nan), 1.0
        pb = tl.playback
        assert pb is not None
        values.fill(np.nan)
        pb.clip.sample_into(ct, values)
        if tl.finished(t) and not state.clip_done_reported:
            state.clip_done_reported = True
            out.events.append({"event": "clip", "t": t, "state": "finished", "clip": pb.clip.name})
        return solve_channels(state, params, out, values), 1.0
    if mode is Mode.STREAM or mode is Mode.LIVE:
        live = mode is Mode.LIVE
        buffer: Any = state.live if live else state.stream
        age = buffer.starved_for(t)
        hold_s = sf.watchdog_hold_s
        if live and state.live is not None and state.live.watchdog_s is not None:
            hold_s = state.live.watchdog_s  # the input's own loss time (sACN: E1.31 data loss)
        if age > hold_s + (sf.watchdog_neutral_s - sf.watchdog_hold_s):
            out.events.append({"event": "watchdog", "t": t, "stage": "neutral", "age": age, "source": state.source})
            _set_mode(state, Mode.NEUTRAL)
            buffer.clear()
            return state.safety.neutral.copy(), sf.safe_speed
        if age > hold_s:
            if state.watchdog_stage != "hold":
                state.watchdog_stage = "hold"
                out.events.append({"event": "watchdog", "t": t, "stage": "hold", "age": age, "source": state.source})
            return np.full(n, np.nan), 1.0
        state.watchdog_stage = ""
        if not buffer.evaluate(t, values):
            return np.full(n, np.nan), 1.0
        return solve_channels(state, params, out, values), 1.0
    if mode is Mode.POSE and state.pose_target is not None:
        return state.pose_target, state.pose_speed
    if mode is Mode.NEUTRAL:
        return state.safety.neutral.copy(), sf.safe_speed
    return np.full(n, np.nan), 1.0


def solve_channels(state: CoreState, params: CoreParams, out: CycleOutputs, values: np.ndarray) -> np.ndarray:
    """Channel vector (config units, NaN = not addressed) → actuator targets (SI, NaN = hold).

    Explicit actuator channels win over group channels, which win over solved targets."""
    cm = params.channels
    x = np.full(cm.n_actuators, np.nan)
    for s, a, b in cm.target_blocks:
        seg = values[a:b]
        if not np.isfinite(seg).any():
            continue
        solver = state.solvers[s]
        p, extra = solver.solve_array(seg, state.shaper.q)
        np.copyto(x, p, where=np.isfinite(p))
        if extra:
            state.extra = extra
    if cm.group_channel.size:
        gv = values[cm.group_channel]
        ok = np.isfinite(gv)
        if ok.any():
            x[cm.group_member[ok]] = gv[ok] * cm.group_factor[ok]
    av = values[:cm.n_actuators]
    ok = np.isfinite(av)
    x[ok] = av[ok] * cm.act_scale[ok]
    return x


# ---------------------------------------------------------------------- lifecycle
def _event(out: CycleOutputs, t: float, kind: str, **data: Any) -> None:
    out.events.append({"event": kind, "t": t, **data})


def _set_lifecycle(state: CoreState, out: CycleOutputs, t: float, new: Lifecycle) -> None:
    if new is not state.lifecycle:
        previous, state.lifecycle = state.lifecycle, new
        _event(out, t, "lifecycle", state=new.value, previous=previous.value)


def _set_mode(state: CoreState, mode: Mode) -> None:
    if mode is not state.mode:
        state.mode = mode
        state.watchdog_stage = ""


def _stop_motion(state: CoreState) -> None:
    _set_mode(state, Mode.HOLD)
    state.timeline.stop()
    state.stream.clear()
    if state.live is not None:
        state.live.clear()
    state.pose_target = None
    state.source = None


def _take_over(state: CoreState, mode: Mode, source: str) -> None:
    """``source`` becomes the one driving the head (the last active source wins): the others stop."""
    if mode is not Mode.CLIP:
        state.timeline.stop()
    if mode is not Mode.STREAM or state.mode is not Mode.STREAM:
        state.stream.clear()
    if state.live is not None and (mode is not Mode.LIVE or state.mode is not Mode.LIVE
                                   or state.live.source != source):
        state.live.clear(source if mode is Mode.LIVE else None)
    state.pose_target = None
    _set_mode(state, mode)
    state.source = source


def _reset_solvers(state: CoreState) -> None:
    state.guard_ok = None
    q = state.shaper.q
    for s in state.solvers:
        s.reset_array(q)


def _torque_off(params: CoreParams, out: CycleOutputs, state: CoreState) -> None:
    for name, _ in params.buses:
        if state.bus_states.get(name) == "active":
            out.bus_requests.append((name, "disable"))


def _fail_transition(state: CoreState, out: CycleOutputs, exc: E.LikenessError) -> None:
    tr = state.transition
    state.transition = None
    if tr is not None and tr.token is not None:
        out.replies.append((tr.token, {"error": error_body(exc)}))


def _fault(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, source: str, message: str,
           bus: str | None = None) -> None:
    """Enter FAULT: stop commanding, torque off as configured, publish the event."""
    if state.lifecycle in (Lifecycle.FAULT, Lifecycle.ESTOP, Lifecycle.UNCONFIGURED):
        return
    faults = {f"{b}/{d}": [c, m] for b, fs in state.bus_faults.items() for d, (c, m) in fs.items()}
    state.fault_info = {"source": source, "message": message, "t": t, "bus": bus, "faults": faults}
    _fail_transition(state, out, E.Faulted(f"fault: {message}"))
    _stop_motion(state)
    _reset_solvers(state)
    _set_lifecycle(state, out, t, Lifecycle.FAULT)
    out.events.append({"event": "fault", **state.fault_info})
    if params.cfg.safety.fault_action == "disable":
        _torque_off(params, out, state)


def _estop(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, reason: str) -> None:
    if state.lifecycle is Lifecycle.UNCONFIGURED:
        return
    state.estop_reason = reason
    _fail_transition(state, out, E.EStopLatched(f"e-stop: {reason}"))
    _stop_motion(state)
    _reset_solvers(state)
    if state.lifecycle is not Lifecycle.ESTOP:
        _set_lifecycle(state, out, t, Lifecycle.ESTOP)
        _event(out, t, "estop", reason=reason)
    if params.cfg.safety.estop_action == "disable":
        _torque_off(params, out, state)


def _require_ready(state: CoreState) -> None:
    if state.lifecycle is Lifecycle.ESTOP:
        raise E.EStopLatched(f"e-stop is latched ({state.estop_reason}); send reset")
    if state.lifecycle is Lifecycle.FAULT:
        msg = (state.fault_info or {}).get("message", "")
        raise E.Faulted(f"head is in FAULT ({msg}); send reset")
    if state.transition is not None:
        raise E.BadState(f"a {state.transition.op} is in progress")


def _require_active(state: CoreState, op: str) -> None:
    _require_ready(state)
    if state.lifecycle is not Lifecycle.ACTIVE:
        raise E.BadState(f"{op} needs lifecycle active (is {state.lifecycle.value}); send enable")


def _bus_result(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, bus: str, op: str, ok: bool,
                message: str) -> None:
    tr = state.transition
    if tr is None or tr.op != op or bus not in tr.pending:
        if not ok:
            _event(out, t, "bus", bus=bus, op=op, ok=False, message=message)
        return
    tr.pending.discard(bus)
    if not ok:
        tr.failed.append(f"bus {bus}: {message}")


def _check_transition(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    tr = state.transition
    if tr is None:
        return
    if tr.pending and t - tr.since > TRANSITION_TIMEOUT_S:
        tr.failed.append(f"no answer from bus {', '.join(sorted(tr.pending))} within {TRANSITION_TIMEOUT_S:g} s")
        tr.pending.clear()
    if tr.pending:
        return
    if not tr.failed:
        # A bus answers its request before its next feedback shows the new state: wait (briefly) for the feedback
        # of the buses asked to agree, so the lifecycle never runs ahead of what the buses report.
        if tr.answered is None:
            tr.answered = t
        want = "active" if tr.op == "enable" else "inactive"
        lagging = [b for b in tr.requested if state.bus_states[b] != want]
        if lagging and t - tr.answered <= FEEDBACK_LAG_S:
            return
        if lagging and tr.op == "enable":
            tr.failed.append(f"bus {', '.join(lagging)} not active {FEEDBACK_LAG_S:g} s after enabling")
    state.transition = None
    if tr.op == "enable":
        if tr.failed:
            _torque_off(params, out, state)
            if tr.token is not None:
                out.replies.append((tr.token, {"error": error_body(
                    E.HardwareError("enable failed: " + "; ".join(tr.failed)))}))
            return
        q = np.where(np.isfinite(state.measured), state.measured, state.shaper.q)
        state.shaper.reset(np.clip(q, state.safety.lo, state.safety.hi))
        _reset_solvers(state)
        state.enabled_at = t
        _stop_motion(state)
        _set_lifecycle(state, out, t, Lifecycle.ACTIVE)
        if tr.token is not None:
            out.replies.append((tr.token, {"lifecycle": state.lifecycle.value}))
    elif tr.op == "disable":
        if tr.token is not None:
            if tr.failed:
                out.replies.append((tr.token, {"error": error_body(
                    E.HardwareError("disable failed: " + "; ".join(tr.failed)))}))
            else:
                out.replies.append((tr.token, {"lifecycle": state.lifecycle.value}))
    elif tr.op == "reset":
        still = [b for b, s in state.bus_states.items() if s == "fault"]
        if tr.failed or still:
            detail = "; ".join(tr.failed) or f"bus {', '.join(still)} still in FAULT"
            if tr.token is not None:
                kind = E.HardwareError if tr.failed else E.Faulted
                out.replies.append((tr.token, {"error": error_body(kind(f"reset failed: {detail}"))}))
            return
        state.fault_info = None
        state.estop_reason = None
        _set_lifecycle(state, out, t, Lifecycle.INACTIVE)
        if tr.token is not None:
            out.replies.append((tr.token, {"lifecycle": state.lifecycle.value}))


# ---------------------------------------------------------------------- command handlers
def _on_enable(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Enable) -> dict | None:
    if state.lifecycle is Lifecycle.ACTIVE and state.transition is None:
        return {"lifecycle": state.lifecycle.value}
    _require_ready(state)
    if state.lifecycle is not Lifecycle.INACTIVE:
        raise E.BadState(f"enable needs lifecycle inactive (is {state.lifecycle.value})")
    pending = set()
    for name, _ in params.buses:
        if not state.bus_connected[name]:
            raise E.HardwareError(f"enable failed: bus {name} is not connected")
        if state.bus_states[name] == "fault":
            raise E.Faulted(f"bus {name} is in FAULT; send reset")
        if state.bus_states[name] != "active":
            out.bus_requests.append((name, "enable"))
            pending.add(name)
    state.transition = Transition("enable", cmd.token, t, pending)
    return None  # answered when the buses are active


def _on_disable(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Disable) -> dict | None:
    _stop_motion(state)
    if state.transition is not None and state.transition.op == "enable":
        _fail_transition(state, out, E.BadState("enable cancelled by disable"))
    if state.lifecycle is Lifecycle.ACTIVE or any(s == "active" for s in state.bus_states.values()):
        pending = set()
        for name, _ in params.buses:
            if state.bus_states[name] == "active":
                out.bus_requests.append((name, "disable"))
                pending.add(name)
        if state.lifecycle is Lifecycle.ACTIVE:
            _set_lifecycle(state, out, t, Lifecycle.INACTIVE)
        if pending and state.transition is None:
            state.transition = Transition("disable", cmd.token, t, pending)
            return None
    return {"lifecycle": state.lifecycle.value}


def _on_estop(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.EStop) -> dict:
    _estop(state, params, out, t, cmd.reason)
    return {"lifecycle": state.lifecycle.value}


def _on_reset(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Reset) -> dict | None:
    if state.transition is not None:
        _fail_transition(state, out, E.BadState("cancelled by reset"))
    _stop_motion(state)
    _reset_solvers(state)
    pending = set()
    for name, _ in params.buses:
        s = state.bus_states[name]
        if s in ("active", "fault") or not state.bus_connected[name]:
            out.bus_requests.append((name, "reset"))
            pending.add(name)
    if state.lifecycle is Lifecycle.ACTIVE:
        _set_lifecycle(state, out, t, Lifecycle.INACTIVE)
    state.transition = Transition("reset", cmd.token, t, pending)
    _check_transition(state, params, out, t)  # nothing to wait for: answers now
    return None


def _on_status(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Status) -> dict:
    body = _snapshot(state, params, t)
    body.update({
        "estop": state.estop_reason, "fault": state.fault_info,
        "moving": bool(np.any(np.abs(state.shaper.v) > 1e-4)),
        "timeline": state.timeline.describe(t), "stream": state.stream.stats(),
        "recording": None if state.recording is None else {"name": state.recording, "samples": state.record_total},
        "clip_bytes": state.clip_bytes,
    })
    if state.mode is Mode.POSE and state.pose_target is not None:
        err = np.abs(state.pose_target - state.shaper.q)
        body["pose_reached"] = bool(np.all(err < 1e-6) and not body["moving"])
        # stopped where the safety stage let it go: at the target, or short of it where the strain guard limited it
        body["pose_settled"] = bool(not body["moving"] and (body["pose_reached"] or state.guard_verdict != "ok"))
    return body


def _on_load_clip(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.LoadClip) -> dict:
    clip = cmd.clip
    old = state.timeline.clips.get(clip.name)
    budget = params.cfg.runtime.clip_memory_bytes
    used = state.clip_bytes - (old.nbytes if old is not None else 0)
    if used + clip.nbytes > budget:
        raise E.TooLarge(f"clip {clip.name!r} needs {clip.nbytes} bytes; {budget - used} of the "
                        f"{budget}-byte clip budget left (unload_clip first)")
    try:
        state.timeline.load(clip)
    except ValueError as exc:
        raise E.TooLarge(str(exc)) from None
    state.clip_bytes = used + clip.nbytes
    return {"clip": clip.name, "duration": clip.duration, "channels": list(clip.channel_names),
            "keys": cmd.key_count}


def _on_unload_clip(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.UnloadClip) -> dict:
    tl = state.timeline
    clip = tl.clips.get(cmd.name)
    if clip is None:
        raise E.NotFound(f"no clip {cmd.name!r} loaded; loaded: {sorted(tl.clips)}")
    if tl.playback is not None and tl.playback.clip is clip:
        _stop_motion(state)
    tl.unload(cmd.name)
    state.clip_bytes -= clip.nbytes
    return {"clip": cmd.name, "clips": sorted(tl.clips)}


def _on_play(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Play) -> dict:
    _require_active(state, "play")
    if cmd.name not in state.timeline.clips:
        raise E.NotFound(f"no clip {cmd.name!r} loaded; loaded: {sorted(state.timeline.clips)}")
    if cmd.at is not None and not t - 3600 <= cmd.at <= t + 3600:
        raise E.BadValue(f"field 'at' must lie within an hour of the daemon clock ({t:.3f})")
    _take_over(state, Mode.CLIP, cmd.source)
    start = state.timeline.play(cmd.name, t, cmd.at, cmd.offset, cmd.speed, cmd.loop)
    state.clip_done_reported = False
    _event(out, t, "clip", state="playing", clip=cmd.name, start=start)
    return {"clip": cmd.name, "start": start, "duration": state.timeline.clips[cmd.name].duration}


def _on_pause(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Pause) -> dict:
    _require_active(state, "pause")
    state.timeline.pause(t)
    return {"timeline": state.timeline.describe(t)}


def _on_resume(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Resume) -> dict:
    _require_active(state, "resume")
    if state.timeline.playback is None:
        raise E.BadState("nothing to resume: no clip is playing")
    state.timeline.resume(t)
    if state.mode is not Mode.CLIP:
        _take_over(state, Mode.CLIP, "api")
    return {"timeline": state.timeline.describe(t)}


def _on_stop(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.StopMotion) -> dict:
    _stop_motion(state)
    return {"mode": state.mode.value}


def _on_seek(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Seek) -> dict:
    _require_active(state, "seek")
    if state.timeline.playback is None:
        raise E.BadState("nothing to seek: no clip is playing")
    state.timeline.seek(t, cmd.time)
    return {"timeline": state.timeline.describe(t)}


def _on_stream(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Stream) -> dict:
    _require_active(state, "stream")
    if state.mode is not Mode.STREAM:
        _take_over(state, Mode.STREAM, "api")
    # Late means behind the play-out point by the time the frames reached the daemon (what the jitter buffer's
    # delay absorbs), not by the time this cycle took them; frames already played past stay late.
    arrival = t if cmd.received is None else min(t, cmd.received)
    counts = state.stream.push(arrival, cmd.times, cmd.channels, cmd.rows)
    if counts["late"]:
        _event(out, t, "dropped_frames", late=counts["late"], total=state.stream.late)
    return {"accepted": counts["ok"], "late": counts["late"], "ahead": counts["ahead"], "full": counts["full"],
            "buffered": state.stream.count, "t": t}


def _on_pose(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Pose) -> dict:
    _require_active(state, "pose")
    values = np.full(params.channels.n, np.nan)
    values[cmd.channels] = cmd.values
    x = solve_channels(state, params, out, values)
    base = state.pose_target if state.mode is Mode.POSE and state.pose_target is not None else state.shaper.q
    target = state.safety.constrain(np.where(np.isfinite(x), x, base), state.shaper.q)
    _take_over(state, Mode.POSE, "api")
    state.pose_target = target
    state.pose_speed = cmd.speed
    # A new pose is judged afresh: the previous pose's "limited" must not make this one look settled before the
    # guard has seen it (``pose_settled`` reads the verdict of the pose in hand).
    state.guard_verdict = "ok"
    return {"targets_si": target.copy(), "speed": cmd.speed}


def _on_live(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Live) -> dict:
    """Values from a live input: it takes over (the last active source wins) unless it only repeats itself."""
    _require_active(state, f"{cmd.source} input")
    live = state.live
    assert live is not None
    if state.mode is not Mode.LIVE or live.source != cmd.source:
        if not cmd.takeover:
            return {"t": t, "ignored": True}
        _take_over(state, Mode.LIVE, cmd.source)
    arrival = t if cmd.received is None else min(t, cmd.received)
    if cmd.at is not None and cmd.at > arrival + params.cfg.runtime.stream_max_ahead_s:
        raise E.BadValue(f"time tag {cmd.at - arrival:.3f} s ahead; at most "
                        f"{params.cfg.runtime.stream_max_ahead_s:g} s")
    if not live.push(arrival, cmd.channels, cmd.values, cmd.at, cmd.watchdog_s):
        raise E.TooLarge("too many timed updates waiting")
    return {"t": t}


def _on_timecode(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Timecode) -> dict:
    """A timecode sample: the chase follows it; a lock or a jump hands the head to the timecode (when active)."""
    chase = state.chase
    if chase is None:
        raise E.BadState("no timecode input is configured ([inputs.timecode])")
    change = chase.feed(cmd.seconds, min(t, cmd.received), cmd.fps, cmd.rate, cmd.label, cmd.full)
    if change:
        _event(out, t, "timecode", state=chase.state, change=change, timecode=chase.label, rate=chase.rate)
        if state.lifecycle is Lifecycle.ACTIVE and state.transition is None:
            _take_over(state, Mode.CLIP, "timecode")
            _chase_apply(state, out, t)
    return {"state": chase.state}


def _chase_step(state: CoreState, out: CycleOutputs, t: float) -> None:
    """Advance the chase (dropout → freewheel → hold) and, while the timecode drives, place the clip."""
    chase = state.chase
    assert chase is not None
    change = chase.update(t)
    if change:
        _event(out, t, "timecode", state=chase.state, change=change, timecode=chase.label, rate=chase.rate)
    if state.source == "timecode" and state.mode is Mode.CLIP and state.lifecycle is Lifecycle.ACTIVE:
        _chase_apply(state, out, t)


def _chase_apply(state: CoreState, out: CycleOutputs, t: float) -> None:
    """The timeline plays the chased clip at the chased clip time (paused while the chase holds)."""
    chase = state.chase
    assert chase is not None
    tl = state.timeline
    tc = chase.position(t)
    sel = None if tc is None else chase.clip_at(tc)
    if sel is None or sel[0] not in tl.clips:
        tl.stop()  # before the first chased clip (or it is not loaded): hold
        return
    name, ct = sel
    pb = tl.playback
    if pb is None or pb.clip.name != name:
        tl.play(name, t, None, ct, 1.0, False)
        state.clip_done_reported = False
        _event(out, t, "clip", state="playing", clip=name, start=t - ct, source="timecode")
        pb = tl.playback
        assert pb is not None
    if ct < pb.clip.duration:
        state.clip_done_reported = False
    pb.offset, pb.start, pb.speed = ct, t, 1.0
    pb.paused_at = ct if chase.state == CHASE_HOLD else None


def _on_record(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Record) -> dict:
    if cmd.action == "start":
        if state.recording is not None:
            raise E.BadState(f"already recording {state.recording!r}")
        n = len(params.names)
        if state.record_rows is None:
            # rows are handed out every telemetry period, so a few periods of rows is all the core ever holds
            state.record_rows = np.empty((8 * params.telemetry_every + 8, 1 + 2 * n))
        state.recording = cmd.name
        state.record_count = state.record_total = 0
        state.record_t0 = t
        _event(out, t, "record", state="started", name=cmd.name)
        return {"recording": cmd.name}
    if state.recording is None:
        raise E.BadState("not recording")
    name, state.recording = state.recording, None
    _flush_record(state, out)
    _event(out, t, "record", state="stopped", name=name, samples=state.record_total)
    return {"recording": name, "samples": state.record_total, "stopped": True}


def _record(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    if state.recording is None or state.record_rows is None:
        return
    if state.record_total >= params.record_capacity:
        return
    rows = state.record_rows
    if state.record_count >= rows.shape[0]:
        _flush_record(state, out)
    n = len(params.names)
    row = rows[state.record_count]
    row[0] = t - state.record_t0
    row[1:1 + n] = state.shaper.q
    row[1 + n:] = state.measured
    state.record_count += 1
    state.record_total += 1
    if state.record_count >= params.telemetry_every:
        _flush_record(state, out)


def _flush_record(state: CoreState, out: CycleOutputs) -> None:
    if state.record_rows is None or not state.record_count:
        return
    block = state.record_rows[:state.record_count].copy()
    out.record = block if out.record is None else np.vstack([out.record, block])
    state.record_count = 0


_HANDLERS: dict[type, Any] = {
    C.Enable: _on_enable, C.Disable: _on_disable, C.EStop: _on_estop, C.Reset: _on_reset, C.Status: _on_status,
    C.LoadClip: _on_load_clip, C.UnloadClip: _on_unload_clip, C.Play: _on_play, C.Pause: _on_pause,
    C.Resume: _on_resume, C.StopMotion: _on_stop, C.Seek: _on_seek, C.Stream: _on_stream, C.Pose: _on_pose,
    C.Record: _on_record, C.Live: _on_live, C.Timecode: _on_timecode,
}


# ---------------------------------------------------------------------- telemetry
def _snapshot(state: CoreState, params: CoreParams, t: float) -> dict[str, Any]:
    """Raw values (SI arrays) for telemetry and status; the API server formats them."""
    body: dict[str, Any] = {
        "t": t, "lifecycle": state.lifecycle.value, "mode": state.mode.value,
        "commanded_si": state.shaper.q.copy(), "measured_si": state.measured.copy(),
        "buses": dict(state.bus_states), "connected": dict(state.bus_connected),
        "connection": {name: dict(info) for name, info in state.bus_links.items()},
        "guard": {"verdict": state.guard_verdict, "refused": state.guard_refused},
        "feedback_age": {name: float(t - state.stamps[idx].max()) if idx.size else 0.0
                         for name, idx in params.buses},
    }
    pb = state.timeline.playback
    if pb is not None:
        body["clip"] = {"name": pb.clip.name, "time": state.timeline.clip_time(t), "duration": pb.clip.duration}
    if state.mode is Mode.STREAM:
        body["stream"] = state.stream.stats()
    body["source"] = state.source
    if state.mode is Mode.LIVE and state.live is not None:
        body["live"] = state.live.stats()
    if state.chase is not None:
        body["clock"] = state.chase.describe(t)
    if state.extra:
        body["extra"] = dict(state.extra)
    return body

