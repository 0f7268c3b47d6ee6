"""The lifecycle stage (after ros2_control): inactive (buses open, torque off) → active → fault or estop (latched) →
``reset`` → inactive.

:class:`LifecycleState` keeps the lifecycle, the bus transition under way (enable, disable and reset run in the bus
processes; the core never waits for them), why the head faulted and the e-stop's reason. The functions here change
only that state and ask for bus transitions; stopping the sources and resetting the solvers on the way is the
composition's part (:mod:`runtime.core.core`), told by their results.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import NamedTuple

from models import errors as E
from runtime.core import commands as C
from runtime.core.buses import BusesState
from runtime.core.cycle import BusOp, CycleOutputs
from runtime.core.events import Body, BusRequestFailed, EStopped, Fault, LifecycleChanged
from runtime.core.params import CoreParams

#: After the buses answered a transition, how long their feedback may take to show the new state.
FEEDBACK_LAG_S = 1.0
#: A bus lifecycle transition that has not answered within this long fails.
TRANSITION_TIMEOUT_S = 15.0


class Lifecycle(enum.Enum):
    """The head's lifecycle state."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FAULT = "fault"
    ESTOP = "estop"


@dataclass
class Transition:
    """A lifecycle request waiting for the buses: which op, whose reply, since when, which buses still pending."""

    op: BusOp
    token: int | None
    since: float
    pending: set[str]
    failed: list[str] = field(default_factory=list)
    requested: set[str] = field(default_factory=set)
    answered: float | None = None  # when the last bus answered

    def __post_init__(self) -> None:
        self.requested = set(self.pending)


@dataclass
class LifecycleState:
    """The lifecycle, the bus transition under way, the fault and the e-stop's reason, when the head went active."""

    lifecycle: Lifecycle = Lifecycle.INACTIVE
    transition: Transition | None = None
    fault: Fault | None = None
    estop_reason: str | None = None
    enabled_at: float = 0.0

    @property
    def commanding(self) -> bool:
        """Active with no transition under way: the sources drive the head."""
        return self.lifecycle is Lifecycle.ACTIVE and self.transition is None


class Trouble(NamedTuple):
    """What supervision found wrong: what found it, the message, the bus (if one), the actuator (if one)."""

    source: str
    message: str
    bus: str | None
    actuator: str | None = None


def set_lifecycle(life: LifecycleState, out: CycleOutputs, t: float, new: Lifecycle) -> None:
    """Change the lifecycle to ``new`` (published when it changes)."""
    if new is not life.lifecycle:
        previous, life.lifecycle = life.lifecycle, new
        out.emit(LifecycleChanged(t, new.value, previous.value))


def fail_transition(life: LifecycleState, out: CycleOutputs, exc: E.LikenessError) -> None:
    """Drop the transition under way, answering its request with ``exc``."""
    tr = life.transition
    life.transition = None
    if tr is not None and tr.token is not None:
        out.refuse(tr.token, exc)


def require_ready(life: LifecycleState) -> None:
    """Refuse while the e-stop is latched, the head is in FAULT or a transition is under way."""
    if life.lifecycle is Lifecycle.ESTOP:
        raise E.EStopLatched(f"e-stop is latched ({life.estop_reason}); send reset")
    if life.lifecycle is Lifecycle.FAULT:
        msg = life.fault.message if life.fault is not None else ""
        raise E.Faulted(f"head is in FAULT ({msg}); send reset")
    if life.transition is not None:
        raise E.BadState(f"a {life.transition.op} is in progress")


def require_active(life: LifecycleState, op: str) -> None:
    """Refuse ``op`` unless the head is ready and active."""
    require_ready(life)
    if life.lifecycle is not Lifecycle.ACTIVE:
        raise E.BadState(f"{op} needs lifecycle active (is {life.lifecycle.value}); send enable")


def torque_off(fb: BusesState, params: CoreParams, out: CycleOutputs) -> None:
    """Ask every active bus to disable."""
    for name, _ in params.buses:
        if fb.states.get(name) == "active":
            out.request(name, "disable")


# ---------------------------------------------------------------------- fault, e-stop, supervision
def enter_fault(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
                trouble: Trouble) -> bool:
    """Enter FAULT (torque off as configured, the event published); False when already stopped (fault, e-stop) or
    unconfigured."""
    if life.lifecycle in (Lifecycle.FAULT, Lifecycle.ESTOP, Lifecycle.UNCONFIGURED):
        return False
    life.fault = Fault(trouble.source, trouble.message, t, trouble.bus, fb.fault_table(), trouble.actuator)
    fail_transition(life, out, E.Faulted(f"fault: {trouble.message}"))
    set_lifecycle(life, out, t, Lifecycle.FAULT)
    out.emit(life.fault)
    if params.cfg.safety.fault_action == "disable":
        torque_off(fb, params, out)
    return True


def enter_estop(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
                reason: str) -> bool:
    """Latch the e-stop (torque off as configured); False when unconfigured."""
    if life.lifecycle is Lifecycle.UNCONFIGURED:
        return False
    life.estop_reason = reason
    fail_transition(life, out, E.EStopLatched(f"e-stop: {reason}"))
    if life.lifecycle is not Lifecycle.ESTOP:
        set_lifecycle(life, out, t, Lifecycle.ESTOP)
        out.emit(EStopped(t, reason))
    if params.cfg.safety.estop_action == "disable":
        torque_off(fb, params, out)
    return True


def supervise(life: LifecycleState, fb: BusesState, params: CoreParams, t: float) -> Trouble | None:
    """Judge the feedback of an active or inactive head with no transition under way: every bus connected (a lost
    bus faults, naming it); a device fault with torque off faults too; when active, every bus active."""
    if life.lifecycle not in (Lifecycle.ACTIVE, Lifecycle.INACTIVE) or life.transition is not None:
        return None
    active = life.lifecycle is Lifecycle.ACTIVE
    for name, _ in params.buses:
        info = fb.connections.get(name)
        lost = info is not None and info.state in ("lost", "reconnecting")
        if not fb.connected[name] and (lost or active):
            why = "; ".join(m for _, m in fb.faults[name].values())
            return Trouble("bus", f"bus {name}: connection lost" + (f" ({why})" if why else ""), name)
    for name, _ in params.buses:  # inactive: a device fault with torque off (a lost heartbeat) faults the head too
        state = fb.states[name]
        if (state != "active") if active else (state == "fault"):
            return Trouble("driver", f"bus {name}: {fb.fault_detail(name)}", name)
    return None  # when active, the feedback's age and the following errors are the watch's (runtime.core.watch)


# ---------------------------------------------------------------------- transitions
def on_enable(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
              cmd: C.Enable) -> Body | None:
    """Ask every bus not yet active to enable; answered when all are (:func:`conclude`)."""
    if life.commanding:
        return {"lifecycle": life.lifecycle.value}
    require_ready(life)
    if life.lifecycle is not Lifecycle.INACTIVE:
        raise E.BadState(f"enable needs lifecycle inactive (is {life.lifecycle.value})")
    pending = set()
    for name, _ in params.buses:
        if not fb.connected[name]:
            raise E.HardwareError(f"enable failed: bus {name} is not connected")
        if fb.states[name] == "fault":
            raise E.Faulted(f"bus {name} is in FAULT; send reset")
        if fb.states[name] != "active":
            out.request(name, "enable")
            pending.add(name)
    life.transition = Transition("enable", cmd.token, t, pending)
    return None  # answered when the buses are active


def on_disable(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
               cmd: C.Disable) -> Body | None:
    """Cancel an enable under way; ask every active bus to disable (answered when they have)."""
    if life.transition is not None and life.transition.op == "enable":
        fail_transition(life, out, E.BadState("enable cancelled by disable"))
    if life.lifecycle is Lifecycle.ACTIVE or any(s == "active" for s in fb.states.values()):
        pending = set()
        for name, _ in params.buses:
            if fb.states[name] == "active":
                out.request(name, "disable")
                pending.add(name)
        if life.lifecycle is Lifecycle.ACTIVE:
            set_lifecycle(life, out, t, Lifecycle.INACTIVE)
        if pending and life.transition is None:
            life.transition = Transition("disable", cmd.token, t, pending)
            return None
    return {"lifecycle": life.lifecycle.value}


def begin_reset(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
                cmd: C.Reset) -> None:
    """Cancel any transition; reset every bus that is active, faulted or lost; answered when they have (at once
    when none needs it: :func:`settle`)."""
    if life.transition is not None:
        fail_transition(life, out, E.BadState("cancelled by reset"))
    pending = set()
    for name, _ in params.buses:
        if fb.states[name] in ("active", "fault") or not fb.connected[name]:
            out.request(name, "reset")
            pending.add(name)
    if life.lifecycle is Lifecycle.ACTIVE:
        set_lifecycle(life, out, t, Lifecycle.INACTIVE)
    life.transition = Transition("reset", cmd.token, t, pending)


def bus_result(life: LifecycleState, out: CycleOutputs, t: float, bus: str, op: str, ok: bool, message: str) -> None:
    """A bus answered a request: the transition waiting for it takes the answer; a failure nobody waits for is
    published."""
    tr = life.transition
    if tr is None or tr.op != op or bus not in tr.pending:
        if not ok:
            out.emit(BusRequestFailed(t, bus, op, message))
        return
    tr.pending.discard(bus)
    if not ok:
        tr.failed.append(f"bus {bus}: {message}")


def settle(life: LifecycleState, fb: BusesState, t: float) -> Transition | None:
    """The transition under way, taken off once it is over: every bus answered (or the wait timed out) and their
    feedback shows the new state (or had its time to). None while it is still under way."""
    tr = life.transition
    if tr is None:
        return None
    if tr.pending and t - tr.since > TRANSITION_TIMEOUT_S:
        tr.failed.append(f"no answer from bus {', '.join(sorted(tr.pending))} within {TRANSITION_TIMEOUT_S:g} s")
        tr.pending.clear()
    if tr.pending:
        return None
    if not tr.failed:
        # A bus answers its request before its next feedback shows the new state: wait (briefly) for the feedback
        # of the buses asked to agree, so the lifecycle never runs ahead of what the buses report.
        if tr.answered is None:
            tr.answered = t
        want = "active" if tr.op == "enable" else "inactive"
        lagging = [b for b in tr.requested if fb.states[b] != want]
        if lagging and t - tr.answered <= FEEDBACK_LAG_S:
            return None
        if lagging and tr.op == "enable":
            tr.failed.append(f"bus {', '.join(lagging)} not active {FEEDBACK_LAG_S:g} s after enabling")
    life.transition = None
    return tr


def conclude(life: LifecycleState, fb: BusesState, params: CoreParams, out: CycleOutputs, t: float,
             tr: Transition) -> None:
    """Carry out the end of a settled transition and answer its request: an enable goes active (or torques off
    again), a reset leaves FAULT and e-stop for inactive unless a bus is still faulted."""
    if tr.op == "enable":
        if tr.failed:
            torque_off(fb, params, out)
            _answer(out, tr, E.HardwareError("enable failed: " + "; ".join(tr.failed)))
            return
        life.enabled_at = t
        set_lifecycle(life, out, t, Lifecycle.ACTIVE)
    elif tr.op == "disable":
        if tr.failed:
            _answer(out, tr, E.HardwareError("disable failed: " + "; ".join(tr.failed)))
            return
    else:
        still = [b for b, s in fb.states.items() if s == "fault"]
        if tr.failed or still:
            detail = "; ".join(tr.failed) or f"bus {', '.join(still)} still in FAULT"
            kind = E.HardwareError if tr.failed else E.Faulted
            _answer(out, tr, kind(f"reset failed: {detail}"))
            return
        life.fault = None
        life.estop_reason = None
        set_lifecycle(life, out, t, Lifecycle.INACTIVE)
    if tr.token is not None:
        out.reply(tr.token, {"lifecycle": life.lifecycle.value})


def _answer(out: CycleOutputs, tr: Transition, exc: E.LikenessError) -> None:
    if tr.token is not None:
        out.refuse(tr.token, exc)
