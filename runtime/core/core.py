"""The control core: one explicit state object and a pure ``step(state, params, inputs) -> outputs``.

A cycle runs its stages in order, each a small system with its own part of the state (:mod:`runtime.core.state`):

- **read** (:mod:`~runtime.core.buses`): the latest feedback of every bus (a snapshot the runner took without
  blocking) becomes the measured positions;
- **commands**: ready-made commands from the API server (e-stop first, whatever else is queued), dispatched to the
  system whose state they change, and the outcomes of bus lifecycle requests (enable, disable, reset run in the bus
  processes, asynchronously);
- **lifecycle** (:mod:`~runtime.core.lifecycle`): settle the bus transition under way; supervise the feedback (bus
  states and disconnections become faults);
- **watch** (:mod:`~runtime.core.watch`), while commanding: each bus's feedback age (an event when late, a fault
  when too late) and each actuator's following error (a fault when it stays too large);
- **chase** (:mod:`~runtime.core.chasing`): the timecode chase places its clip;
- **sources** (:mod:`~runtime.core.sources`): the active source (clip, stream, live values, pose, neutral, hold)
  gives a channel vector or actuator targets;
- **solve** (:mod:`~runtime.core.solve`): channel vector → actuator targets (actuator channels, groups, solvers);
- **safety**: group constraints and limits, the skin-strain guard (:mod:`~runtime.core.guard`), and the motion
  shaper (:mod:`~runtime.core.shape`);
- **write**: the shaped command vector, which the runner posts to the bus processes (:func:`control` ends here);
- **record** (:mod:`~runtime.core.recorder`) and telemetry (:mod:`~runtime.core.status`), after the post
  (:func:`report`).

The core has no threads, sockets, clocks or globals: time comes in with the inputs, so it can be stepped in tests
and replayed from a recording of its inputs, bit for bit. Lifecycle (after ros2_control): unconfigured → inactive
(buses open, torque off) → active (commanding) → fault or estop (latched) → ``reset`` → inactive.
"""

from __future__ import annotations

from typing import assert_never

import numpy as np

from runtime.core import buses, chasing, guard, lifecycle, recorder, shape, solve, sources, status, watch
from runtime.core import commands as C
from runtime.core.cycle import CycleInputs, CycleOutputs
from runtime.core.events import Body, OutOfRange
from runtime.core.params import CoreParams
from runtime.core.state import CoreState

#: What the loop runner integrates against: the core's ports, parameters and state, and the functions that step it.
__all__ = ["control", "estop", "fault", "report", "solve_channels", "step", "take_commands"]


# ====================================================================== the step
def step(state: CoreState, params: CoreParams, inputs: CycleInputs) -> CycleOutputs:
    """Advance the core by one cycle at time ``inputs.t``; with ``inputs.between_cycles`` only take the commands
    (and e-stop) that arrived between two cycles. With :func:`take_commands` and :func:`fault` (which the runner
    calls when a step raised), the only functions that change ``state``. The cycle is :func:`control` then
    :func:`report`; the runner posts the write between the two, so the recording and the telemetry snapshot do not
    delay it."""
    out = control(state, params, inputs)
    if not inputs.between_cycles:
        report(state, params, out, inputs.t)
    return out


def control(state: CoreState, params: CoreParams, inputs: CycleInputs) -> CycleOutputs:
    """The cycle up to its write (read, commands, lifecycle, watch, chase, sources, solve, safety): :func:`step`
    without the recorded row and the telemetry."""
    if inputs.between_cycles:
        return take_commands(state, params, inputs)
    out = CycleOutputs()
    t = inputs.t
    buses.read(state.feedback, params, inputs.buses, t)
    buses.announce_connections(state.feedback, out, t)
    _commands(state, params, inputs, out)
    for result in inputs.results:
        lifecycle.bus_result(state.life, out, t, *result)
    _settle(state, params, out, t)
    trouble = lifecycle.supervise(state.life, state.feedback, params, t)
    if trouble is None and state.life.commanding:
        trouble = _watch(state, params, out, t)
    if trouble is not None:
        _enter_fault(state, params, out, t, trouble)
    if state.chase is not None:
        chasing.follow(state.chase, state.sources, state.life, out, t)
    if state.life.commanding:
        _control(state, params, out, t)
        watch.post(state.watch, out.write)
    state.cycle += 1
    state.last_t = t
    return out


def report(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    """The cycle after its write: this cycle's recorded row and, every telemetry period, the telemetry snapshot."""
    recorder.record(state.recorder, params, out, t, state.shaper.q, state.feedback.measured)
    if state.cycle % params.telemetry_every == 0:
        out.telemetry = status.snapshot(state, params, t)


def take_commands(state: CoreState, params: CoreParams, inputs: CycleInputs) -> CycleOutputs:
    """Commands that arrived between two cycles, taken at once so their replies (and stream frames) do not wait for
    the next cycle; the bus feedback is taken in, nothing is solved or written."""
    out = CycleOutputs()
    if inputs.buses:
        buses.read(state.feedback, params, inputs.buses, inputs.t)  # bus states as the commands find them
    _commands(state, params, inputs, out)
    return out


def _control(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    """sources → solve → safety (limits, strain guard, shaper) → write."""
    try:
        drive = sources.sample(state.sources, params, state.safety.neutral, out, t)
        targets = solve_channels(state, params, out, drive.values) if drive.solve else drive.values
        hold = np.isnan(targets)
        if params.guard is not None:  # constrains, then keeps to what the skin takes
            targets = guard.guarded(state.guard, params.guard, state.safety, state.shaper.q, targets)
        else:
            targets = state.safety.constrain(targets, state.shaper.q)
        out.write = shape.shape(state.shaper, targets, drive.speed, hold, params.cfg.safety.safe_speed,
                                shape.advance(params.period, t, state.last_t))
        if state.out_of_range is not None:  # actuators enabled outside their limits, being brought back
            still = state.shaper.outside
            _report_range(state, params, out, t, state.out_of_range & ~still, "inside")
            state.out_of_range = still if still.any() else None
    except Exception as exc:  # a failing solver or a bug: nothing is written, the head faults, replies stand
        out.write = None
        fault(state, params, out, t, "control loop", f"control cycle failed: {type(exc).__name__}: {exc}")


def _report_range(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, which: np.ndarray,
                  where: str) -> None:
    """An ``out_of_range`` event for each actuator in ``which`` (found outside its limits, or back inside)."""
    for i in np.flatnonzero(which):
        k = params.scale[i]
        out.emit(OutOfRange(t, params.names[i], where, float(state.shaper.q[i] / k), float(state.safety.lo[i] / k),
                            float(state.safety.hi[i] / k), params.units[i]))


def _watch(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> lifecycle.Trouble | None:
    """The feedback's age per bus, then each actuator's following error (:mod:`~runtime.core.watch`)."""
    w, wp, fb = state.watch, params.watch, state.feedback
    ages = watch.feedback_ages(fb.reported, t, state.life.enabled_at)
    found = watch.check_feedback(w, wp, params.buses, ages, out, t) or watch.check_following(
        w, wp, params.names, params.buses, params.bus_of, ages, fb.measured, params.scale, params.units, t)
    return None if found is None else lifecycle.Trouble(found.source, found.message, found.bus, found.actuator)


def solve_channels(state: CoreState, params: CoreParams, out: CycleOutputs, values: np.ndarray) -> np.ndarray:
    """Channel vector (config units, NaN = not addressed) → actuator targets (SI, NaN = hold).

    Explicit actuator channels win over group channels, which win over solved targets."""
    return solve.to_targets(state.solve, params.channels, state.shaper.q, values)


# ====================================================================== commands
def _commands(state: CoreState, params: CoreParams, inputs: CycleInputs, out: CycleOutputs) -> None:
    t = inputs.t
    if inputs.estop is not None:
        estop(state, params, out, t, inputs.estop)
    cmds = inputs.commands
    if any(isinstance(c, C.EStop) for c in cmds):  # e-stop preempts whatever else is queued with it
        cmds = tuple(c for c in cmds if isinstance(c, C.EStop)) + tuple(c for c in cmds if not isinstance(c, C.EStop))
    for cmd in cmds:
        try:
            body = _handle(state, params, out, t, cmd)
        except Exception as exc:  # refused (a models.errors kind: its protocol code) or a bug (internal): answered,
            out.refuse(cmd.token, exc)  # and the other commands still run
        else:
            if body is not None and not (isinstance(cmd, C.Live) and cmd.quiet):
                out.reply(cmd.token, body)


def _handle(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Command) -> Body | None:
    """Carry out one command in the system whose state it changes; its reply (None: answered later)."""
    src, life, fb = state.sources, state.life, state.feedback
    match cmd:
        case C.Enable():
            return lifecycle.on_enable(life, fb, params, out, t, cmd)
        case C.Disable():
            sources.stop_motion(src)
            return lifecycle.on_disable(life, fb, params, out, t, cmd)
        case C.EStop():
            estop(state, params, out, t, cmd.reason)
            return {"lifecycle": life.lifecycle.value}
        case C.Reset():
            lifecycle.begin_reset(life, fb, params, out, t, cmd)
            _halt(state)
            _settle(state, params, out, t)  # nothing to wait for: answers now
            return None
        case C.Status():
            return status.status(state, params, t)
        case C.LoadClip():
            return sources.on_load_clip(src, params, cmd)
        case C.UnloadClip():
            return sources.on_unload_clip(src, cmd)
        case C.Play():
            return sources.on_play(src, life, out, t, cmd)
        case C.Pause():
            return sources.on_pause(src, life, t)
        case C.Resume():
            return sources.on_resume(src, life, t)
        case C.StopMotion():
            sources.stop_motion(src)
            return {"mode": src.mode.value}
        case C.Seek():
            return sources.on_seek(src, life, t, cmd)
        case C.Stream():
            return sources.on_stream(src, life, out, t, cmd)
        case C.Pose():
            return _pose(state, params, out, cmd)
        case C.Record():
            return recorder.on_record(state.recorder, params, out, t, cmd)
        case C.Live():
            return sources.on_live(src, life, params, t, cmd)
        case C.Timecode():
            return chasing.on_timecode(state.chase, src, life, out, t, cmd)
        case _:
            assert_never(cmd)


def _pose(state: CoreState, params: CoreParams, out: CycleOutputs, cmd: C.Pose) -> Body:
    """A pose: its channels solved, held where not addressed, constrained; it takes over."""
    src = state.sources
    lifecycle.require_active(state.life, "pose")
    values = np.full(params.channels.n, np.nan)
    values[cmd.channels] = cmd.values
    x = solve_channels(state, params, out, values)
    base = src.pose_target if src.mode is sources.Mode.POSE and src.pose_target is not None else state.shaper.q
    target = state.safety.constrain(np.where(np.isfinite(x), x, base), state.shaper.q)
    sources.hold_pose(src, target, cmd.speed)
    guard.judge_afresh(state.guard)
    return {"targets_si": target.copy(), "speed": cmd.speed}


# ====================================================================== lifecycle across the systems
def fault(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, source: str, message: str,
          bus: str | None = None) -> None:
    """Enter FAULT: stop commanding, torque off as configured, publish the event (the runner calls this when a step
    raised)."""
    _enter_fault(state, params, out, t, lifecycle.Trouble(source, message, bus))


def estop(state: CoreState, params: CoreParams, out: CycleOutputs, t: float, reason: str) -> None:
    """Latch the e-stop: stop commanding, torque off as configured, publish the event."""
    if lifecycle.enter_estop(state.life, state.feedback, params, out, t, reason):
        _halt(state)


def _enter_fault(state: CoreState, params: CoreParams, out: CycleOutputs, t: float,
                 trouble: lifecycle.Trouble) -> None:
    if lifecycle.enter_fault(state.life, state.feedback, params, out, t, trouble):
        _halt(state)


def _halt(state: CoreState) -> None:
    """Every source stops and the solvers, the guard and the watch start afresh (enable, fault, e-stop, reset)."""
    sources.stop_motion(state.sources)
    _restart_solvers(state)
    state.watch.restart()


def _restart_solvers(state: CoreState) -> None:
    guard.forget(state.guard)
    solve.reset(state.solve, state.shaper.q)


def _settle(state: CoreState, params: CoreParams, out: CycleOutputs, t: float) -> None:
    """End the bus transition under way once it is over; an enable that succeeded commands from where the head is."""
    tr = lifecycle.settle(state.life, state.feedback, t)
    if tr is None:
        return
    if tr.op == "enable" and not tr.failed:
        outside = shape.restart(state.shaper, state.safety, state.feedback.measured, state.feedback.written)
        state.out_of_range = outside if outside.any() else None
        _report_range(state, params, out, t, outside, "outside")
        _halt(state)
    lifecycle.conclude(state.life, state.feedback, params, out, t, tr)
