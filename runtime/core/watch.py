"""The feedback watch (after ros2_control's and CiA 402 drives' watchdogs): feedback that stops or a drive that stops
following never goes unnoticed while the head is active.

Two checks run every cycle on the feedback the read stage took in:

- **feedback age per bus**: how long ago the bus's devices last reported (the oldest of its actuators' newest samples,
  stamped with the time the device's answer was on the bus). Past ``[buses.NAME] feedback_timeout_s`` a
  ``feedback_late`` event names the bus and the age (and a ``recovered`` one once it has been within the limit for
  :data:`RECOVER_AFTER_S`); past ``feedback_fault_s`` the head faults naming the bus.
- **following error per actuator**: the distance of the measured position from the span of the commands posted in
  the last :data:`LAG_CYCLES` cycles (a posted command reaches the drive one cycle later and the drive reports where
  it was when it took it, so the newest commands are not yet due). Beyond ``max_following_error`` for
  ``following_error_time_s`` the head faults naming the actuator. An actuator whose bus is late is left to the
  feedback age (its measurement is not current).

Both are judged from the moment the head went active (the enable re-reads every device) and start afresh on every
enable.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models import errors as E
from models.headspec import HeadSpec
from models.kernel_support import kernels_available
from models.kernels_aot import kernel
from runtime.config import DaemonConfig
from runtime.core.cycle import CycleOutputs
from runtime.core.events import FeedbackLate

#: ``[buses.NAME] feedback_timeout_s`` when the head does not set it, in control periods.
LATE_PERIODS = 5
#: The commands posted in this many recent cycles are all "what the core commanded" for the following error.
LAG_CYCLES = 3
#: A late bus is ``recovered`` once its feedback has stayed within the limit this long (a bus hovering about its
#: limit stays late rather than publishing a pair of events every few cycles); every new lateness is published at once.
RECOVER_AFTER_S = 0.5
#: ``max_following_error`` when an actuator does not set it: the distance it covers in this long at its max velocity.
FOLLOWING_ERROR_AT_MAX_VELOCITY_S = 0.1
#: ``following_error_time_s`` when an actuator does not set it: longer than the stalls of emulated drives on a loaded
#: host (up to ~0.2 s), short enough that a jammed or slipping actuator stops the show within half a second.
FOLLOWING_ERROR_TIME_S = 0.5


@dataclass(frozen=True)
class WatchParams:
    """The limits, fixed for a run: per bus (in the order of the core's buses) the feedback ages of the event and of
    the fault (s); per actuator the following error (SI) and how long it may be exceeded (s)."""

    late_s: np.ndarray
    fault_s: np.ndarray
    max_error: np.ndarray
    error_time_s: np.ndarray
    bus_index: np.ndarray  # per actuator, its bus's place in the core's buses (-1: none of them)

    @classmethod
    def build(cls, head: HeadSpec, cfg: DaemonConfig, buses: tuple[str, ...], period: float) -> WatchParams:
        """The head's limits with their defaults filled in; ConfigError naming the key when they do not fit the
        loop's period or each other."""
        late, fault = [], []
        for name in buses:
            bus = head.buses[name]
            limit = cfg.safety.feedback_timeout_s if bus.feedback_fault_s is None else bus.feedback_fault_s
            key = f"buses.{name}.feedback_fault_s" if bus.feedback_fault_s is not None else "safety.feedback_timeout_s"
            if limit <= 2.0 * period:
                raise E.ConfigError(f"{head.source}: {key} = {limit!r}: must exceed two loop periods "
                                    f"({2.0 * period:g} s)")
            warn = min(LATE_PERIODS * period, 0.5 * limit) if bus.feedback_timeout_s is None else bus.feedback_timeout_s
            if warn >= limit:
                raise E.ConfigError(f"{head.source}: buses.{name}.feedback_timeout_s = {warn!r}: must be shorter "
                                    f"than the fault limit {key} ({limit:g} s)")
            late.append(warn)
            fault.append(limit)
        max_error = [a.max_velocity * FOLLOWING_ERROR_AT_MAX_VELOCITY_S if a.max_following_error is None
                     else a.max_following_error for a in head.actuators]
        error_time = [FOLLOWING_ERROR_TIME_S if a.following_error_time_s is None else a.following_error_time_s
                      for a in head.actuators]
        bus_index = [buses.index(a.bus) if a.bus in buses else -1 for a in head.actuators]
        return cls(np.array(late), np.array(fault), np.array(max_error), np.array(error_time),
                   np.array(bus_index, dtype=np.int64))


@dataclass
class WatchState:
    """What the watch remembers: the commands posted in the last cycles (rows, newest last; NaN: none yet); per
    actuator since when its following error is beyond the limit (NaN: within) and the largest following error since
    the head went active (telemetry); per late bus the largest age seen, and since when it is within its limit again;
    the following errors of the cycle (a work buffer)."""

    posted: np.ndarray
    over_since: np.ndarray
    peak_error: np.ndarray
    error: np.ndarray
    late: dict[str, float] = field(default_factory=dict)
    fresh_since: dict[str, float] = field(default_factory=dict)

    @classmethod
    def initial(cls, n: int) -> WatchState:
        """Nothing posted, nothing late."""
        return cls(posted=np.full((LAG_CYCLES, n), np.nan), over_since=np.full(n, np.nan), peak_error=np.zeros(n),
                   error=np.zeros(n))

    def restart(self) -> None:
        """Forget the past (the head went active, faulted or stopped commanding)."""
        self.posted.fill(np.nan)
        self.over_since.fill(np.nan)
        self.peak_error.fill(0.0)
        self.late.clear()
        self.fresh_since.clear()


@dataclass(frozen=True)
class Finding:
    """What the watch found wrong: the message, the bus and (for a following error) the actuator."""

    source: str  # "timeout" (feedback age) or "following_error"
    message: str
    bus: str
    actuator: str | None = None


def feedback_ages(reported: dict[str, float], t: float, since: float) -> list[float]:
    """Per bus (in the order of ``reported``), how long ago at ``t`` its devices last reported, counted from
    ``since`` at the earliest."""
    return [t - max(stamp, since) for stamp in reported.values()]


def check_feedback(w: WatchState, wp: WatchParams, buses: tuple[tuple[str, np.ndarray], ...], ages: list[float],
                   out: CycleOutputs, t: float) -> Finding | None:
    """Publish ``feedback_late`` when a bus's age passes its limit (and ``recovered`` once it has stayed within for
    :data:`RECOVER_AFTER_S`); the finding when an age passes its fault limit."""
    for i, (name, _) in enumerate(buses):
        age = ages[i]
        if age > wp.late_s[i]:
            if name not in w.late:
                out.emit(FeedbackLate(t, name, "late", age, float(wp.late_s[i])))
            w.late[name] = max(age, w.late.get(name, 0.0))
            w.fresh_since.pop(name, None)
            if age > wp.fault_s[i]:
                return Finding("timeout", f"bus {name}: no feedback from its devices for {age * 1e3:.0f} ms "
                               f"(limit {wp.fault_s[i]:g} s)", name)
        elif name in w.late and t - w.fresh_since.setdefault(name, t) >= RECOVER_AFTER_S:
            out.emit(FeedbackLate(t, name, "recovered", w.late.pop(name), float(wp.late_s[i])))
            del w.fresh_since[name]
    return None


def check_following(w: WatchState, wp: WatchParams, names: tuple[str, ...], buses: tuple[tuple[str, np.ndarray], ...],
                    bus_of: tuple[str, ...], ages: list[float], measured: np.ndarray, scale: np.ndarray,
                    units: tuple[str, ...], t: float, compiled: bool | None = None) -> Finding | None:
    """The finding when an actuator's following error stayed beyond its limit for its time (the actuators of a bus
    whose feedback is late are skipped: their measurement is not current). Compiled in one call
    (:func:`models._cycle_kernels.following_watch`) where numba is installed (``compiled``), else in numpy: the same
    errors, times and finding."""
    if compiled is None:
        compiled = kernels_available()
    if compiled:
        i = int(kernel("following_watch")(w.posted, measured, wp.bus_index, np.array(ages, dtype=np.float64),
                                          wp.late_s, wp.max_error, wp.error_time_s, w.peak_error, w.over_since,
                                          w.error, t))
        if i < 0:
            return None
    else:
        found = _due_numpy(w, wp, buses, ages, measured, t)
        if found is None:
            return None
        i = found
    error = w.error
    k = scale[i]
    return Finding("following_error",
                   f"actuator {names[i]}: following error {error[i] / k:.3g} {units[i]} beyond "
                   f"{wp.max_error[i] / k:.3g} {units[i]} for {t - w.over_since[i]:.3g} s (bus {bus_of[i]})",
                   bus_of[i], names[i])


def _due_numpy(w: WatchState, wp: WatchParams, buses: tuple[tuple[str, np.ndarray], ...], ages: list[float],
               measured: np.ndarray, t: float) -> int | None:
    """:func:`check_following`'s errors and times in numpy (the reference of the compiled watch): the first actuator
    due to fault, or None."""
    error = following_errors(w.posted, measured, out=w.error)
    for i, (_, idx) in enumerate(buses):
        if ages[i] > wp.late_s[i]:
            error[idx] = 0.0
    np.maximum(w.peak_error, error, out=w.peak_error)
    over = error > wp.max_error
    if not over.any():
        w.over_since.fill(np.nan)
        return None
    w.over_since[~over] = np.nan
    w.over_since[over & np.isnan(w.over_since)] = t
    due = np.flatnonzero(over & (t - w.over_since >= wp.error_time_s))
    return int(due[0]) if due.size else None


def following_errors(posted: np.ndarray, measured: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Per actuator, how far ``measured`` lies outside the span of the commands ``posted`` (rows; NaN rows: none);
    0 where nothing was posted or nothing measured. Into ``out`` when given."""
    lo = np.fmin(posted[0], posted[1], out=out)  # fmin/fmax skip NaN: a row not yet posted; row by row, which
    hi = np.fmax(posted[0], posted[1])  # costs less than a reduction over the rows' axis of so few rows
    for row in posted[2:]:
        np.fmin(lo, row, out=lo)
        np.fmax(hi, row, out=hi)
    np.subtract(lo, measured, out=lo)
    np.subtract(measured, hi, out=hi)
    np.fmax(lo, hi, out=lo)
    return np.fmax(lo, 0.0, out=lo)  # NaN (nothing posted or measured) → 0


def post(w: WatchState, write: np.ndarray | None) -> None:
    """Remember this cycle's posted command (None: nothing posted, the drives keep the last one)."""
    w.posted[:-1] = w.posted[1:]
    w.posted[-1] = w.posted[-2] if write is None else write
