"""The loop runner: the one realtime thread. It owns time, and each cycle it reads → steps the core → writes.

Per cycle: sleep (then spin) to the next absolute deadline; take every bus's latest feedback and the commands that
arrived on the command pipe (never waiting for either); run :func:`runtime.core.core.step`; post the commanded
positions to the buses (:class:`runtime.bus.BusProxy`) and their lifecycle requests; hand replies, events,
telemetry snapshots and recorded rows to the API server (:data:`runtime.loop_messages.FromLoop`).
Only this thread runs under SCHED_FIFO (and pinned to a CPU where allowed); deadline misses, wake-up jitter
and work time are measured every cycle. Overrun policy: a cycle that starts more than a period late skips the
missed deadlines instead of bursting to catch up, and the misses are counted and reported once a second.

Wake on input (``[runtime] wake_on_input``): a live value, a timecode sample or a stream frame due before the next
deadline that reaches the loop between cycles makes the loop run that deadline's cycle at once (at the frame's play
time for a stream frame), with every stage as always (limits, strain guard, shaper, lifecycle, watchdogs), instead
of leaving the value in the pipe for up to a period. The cycle's time is then when it runs; the shaper advances by
the time that passed since the cycle before (never more than a period), so its limits hold in real time and the
drivers' rate guard sees honest stamps. Each period slot still runs one cycle at most (the early one takes its
deadline's place) and none runs closer than ``WAKE_MIN_GAP`` periods after the one before: the buses get no more
writes than at the configured rate. Early cycles are counted (``loop.early`` in ``status``); they have no deadline,
so they add nothing to lateness or misses.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
import zmq

from runtime import ipc
from runtime import loop_messages as L
from runtime.bus import BusProxy
from runtime.core import core as K
from runtime.core.commands import Command, Live, Stream, Timecode
from runtime.core.cycle import BusInput, CycleInputs, CycleOutputs
from runtime.core.params import CoreParams
from runtime.core.state import CoreState
from runtime.cycle_forensics import CycleForensics
from runtime.input_trace import InputTrace
from runtime.loop import LoopStats, RateScheduler, SwitchInterval, drop_realtime, freeze_heap, try_realtime
from runtime.phaselock import PhaseLock

log = logging.getLogger(__name__)

#: Commands taken from the command pipe per cycle at most (the rest wait for the next cycle).
MAX_COMMANDS_PER_CYCLE = 64
STATS_EVERY_S = 0.5
#: Commands arriving between cycles are taken at once unless the next cycle is closer than this.
COMMAND_MARGIN_S = 300e-6
#: An early cycle runs no sooner than this many periods after the cycle before (the bus process has written that one).
WAKE_MIN_GAP = 0.25


def phase_lock(period: float, lead: float, wake_on_input: bool) -> PhaseLock:
    """The loop's phase lock. Without wake on input a frame's cycle runs at its deadline: the lock puts that
    ``lead`` (the hand-over to the loop) after the frames' receipt. With it, a frame runs its cycle as soon as it is
    due (taken, at its time tag or play time) once its period slot has begun: the lock centres the frames' due times
    in their slots (deadline half a period after, the slot's start half a period before), so a frame up to half a
    period early or late still runs its own cycle at once (:attr:`PhaseLock.slotted`, :meth:`Runner._lock_time`)."""
    if wake_on_input:
        return PhaseLock(period, lead=0.5 * period, slotted=True)
    return PhaseLock(period, lead=lead)


class Runner:
    """Runs the core at the configured rate on the calling thread until :meth:`stop`."""

    def __init__(self, params: CoreParams, state: CoreState, buses: Sequence[BusProxy], sock: zmq.Socket,
                 commands: ipc.PipeReader[Command], estop: ipc.EStopFlag, clock: Callable[[], float] = time.monotonic,
                 input_log: list[CycleInputs] | None = None) -> None:
        self.params = params
        self.state = state
        self.buses = list(buses)
        self.sock = sock  # to the server: replies, events, state (runtime.loop_messages.FromLoop)
        self.commands = commands  # from the server: ready-made commands
        self.estop = estop
        self.clock = clock
        self.stats = LoopStats(params.period)
        self.input_log = input_log
        self.output_log: list[np.ndarray | None] | None = [] if input_log is not None else None  # writes, beside inputs
        self.realtime_status = "not started"
        self.ready = threading.Event()
        self._stop = threading.Event()
        self._tickets: dict[tuple[int, int], str] = {}  # (bus index, ticket) → op
        self._signal_estop: str | None = None
        self.native_id = 0
        rt = params.cfg.runtime
        self.wake_on_input = rt.wake_on_input
        self.phase_lock = (phase_lock(params.period, rt.stream_phase_lead_s, rt.wake_on_input)
                           if rt.stream_phase_lock else None)
        self._deadline = 0.0  # the deadline the loop is waiting for (commands taken meanwhile are due then)
        self._early_at: float | None = None  # when the early cycle asked for by an input's arrival runs
        self._last_t = float("-inf")  # the time of the last cycle
        self._carry: list[Command] = []  # commands taken between cycles for the early cycle they woke
        self.trace = InputTrace()  # live values' and stream frames' stamps on their way to the bus
        self.forensics = CycleForensics(params.period)  # what a missed deadline's cycle left as evidence

    def stop(self) -> None:
        self._stop.set()

    def trip_estop(self, reason: str) -> None:
        """E-stop from this process (a signal handler): taken by the next cycle."""
        self._signal_estop = reason

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        rt = self.params.cfg.runtime
        self.native_id = threading.get_native_id()
        if rt.realtime:
            ok, msg = try_realtime(rt.priority)
            if ok:
                msg += _pin_cpu(rt.cpu)
        else:
            ok, msg = False, "realtime priority disabled in config ([runtime] realtime = false)"
        self.realtime_status = msg
        (log.info if ok else log.warning)("%s", msg)
        self._send(L.RealtimeStatus(msg))
        freeze_heap()
        sched = RateScheduler(self.params.period, rt.spin_us * 1e-6, self.clock)
        next_stats = 0.0
        pending_misses = 0
        last_miss_event = 0.0
        self.ready.set()
        try:
            with SwitchInterval(rt.switch_interval_s):
                while not self._stop.is_set():
                    self._deadline = sched.next
                    late, missed = sched.wait(self._idle)
                    woke = self.clock()
                    # The cycle's time is its deadline: the core's trajectory advances in exact periods whatever
                    # the wake-up jitter, and the drivers' rate guard sees the same spacing in the stamps. An early
                    # cycle (wake on input) has no deadline: its time is when it runs.
                    t = woke if sched.early else sched.next - self.params.period
                    self._last_t = t
                    self.forensics.woke(t, late, missed)
                    inputs = self._inputs(t)
                    try:
                        out = K.control(self.state, self.params, inputs)
                        failed = False
                    except Exception as exc:  # a bug or a failing solver: safe state, the loop lives on
                        log.exception("control cycle failed")
                        out, failed = CycleOutputs(), True
                        K.fault(self.state, self.params, out, t, "control loop",
                              f"control cycle failed: {type(exc).__name__}: {exc}")
                    self._write(out, t)  # before the recording and telemetry: they need not delay the bus
                    if self.trace.open_rows:
                        self.trace.applied(woke, self.clock())
                    if not failed:
                        self._report(out, t)
                    if missed:
                        self.stats.missed += missed
                        pending_misses += missed
                    if sched.early:
                        self.stats.early += 1
                    if pending_misses and t - last_miss_event >= 1.0:
                        self._send(L.Event({"event": "deadline_miss", "t": t, "count": pending_misses,
                                            "total": self.stats.missed, "causes": self.forensics.take()}))
                        pending_misses = 0
                        last_miss_event = t
                    self._outbox(out)
                    if t >= next_stats:
                        next_stats = t + STATS_EVERY_S
                        self._send_stats()
                    self.forensics.work_done()
                    if not sched.early:  # an early cycle has no deadline to be late for
                        self.stats.add(late, self.clock() - t, t)
                    if self.phase_lock is not None:
                        sched.next += self.phase_lock.correction()
        except Exception:
            log.exception("control loop crashed")
        finally:
            drop_realtime()

    def _report(self, out: CycleOutputs, t: float) -> None:
        """The cycle's recorded row and telemetry (:func:`runtime.core.core.report`), after its write."""
        try:
            K.report(self.state, self.params, out, t)
        except Exception as exc:  # a bug: safe state, the loop lives on
            log.exception("control cycle failed after its write")
            K.fault(self.state, self.params, out, t, "control loop",
                    f"control cycle failed after its write: {type(exc).__name__}: {exc}")

    def _idle(self, until: float) -> bool:
        """Until ``until``: wait for commands from the server and take them at once (their replies and stream frames
        then need not wait for the next cycle), as long as ``COMMAND_MARGIN_S`` is left before the cycle; later ones
        wait for the cycle (with wake on input, one that moves the head runs it at once: :meth:`_margin_wake`).
        ``select`` times out to the microsecond (``poll`` only to the millisecond, which left the last fraction of a
        millisecond before each cycle unwatched). Returns True when an input's arrival asks for the cycle now (wake on
        input: the module docstring)."""
        fd = self.commands.fileno()
        last_take = until - COMMAND_MARGIN_S
        self._early_at = None
        while True:
            now = self.clock()
            early = self._early_at
            if early is not None and now >= early:
                self._early_at = None
                return True
            left = until - now
            if left <= 0:
                return False
            watch = (last_take if early is None else early) - now
            if self.commands.closed or watch <= 0:
                if early is None and self.wake_on_input and not self.commands.closed:
                    if self._margin_wake(fd, until):
                        return True
                    continue
                time.sleep(left if early is None else early - now)
                continue
            ready, _, _ = select.select((fd,), (), (), watch)
            if not ready:
                continue
            t = self.clock()
            cmds = self._drain(self._deadline)
            if self.wake_on_input and cmds:
                self._wake_for(cmds, t, last_take)
                if self._early_at is not None and self._early_at <= t:  # the cycle runs now and takes them itself
                    self._carry = cmds
                    self._early_at = None
                    return True
            estop = self._estop_now()
            if not cmds and estop is None:
                continue
            inputs = CycleInputs(t, self._bus_inputs(), tuple(cmds), (), estop, between_cycles=True)
            if self.input_log is not None:
                self.input_log.append(inputs)
            try:
                out = K.step(self.state, self.params, inputs)
            except Exception as exc:
                log.exception("taking commands failed")
                out = CycleOutputs()
                K.fault(self.state, self.params, out, t, "control loop",
                      f"taking commands failed: {type(exc).__name__}: {exc}")
            self._write(out, t)
            self._outbox(out)
            self.forensics.between(self.clock() - t)

    def _margin_wake(self, fd: int, until: float) -> bool:
        """The margin before a cycle (``COMMAND_MARGIN_S``), with wake on input: commands that arrive are taken off
        the pipe and kept for that cycle (no step between cycles this close to it), and one that moves the head now
        (:meth:`_wake_for`) runs the cycle at once instead of at its deadline, up to the margin and the spin earlier.
        Returns True for that cycle; False when ``until`` passed, or after commands that do not call for it."""
        left = until - self.clock()
        if left <= 0:
            return False
        ready, _, _ = select.select((fd,), (), (), left)
        if not ready:
            return False
        t = self.clock()
        cmds = self._drain(self._deadline)
        if not cmds:
            return False
        self._carry = self._carry + cmds
        self._wake_for(cmds, t, until)
        if self._early_at is not None and self._early_at <= t:
            self._early_at = None
            return True
        return False

    def _wake_for(self, cmds: Sequence[Command], now: float, last: float) -> None:
        """Ask for the early cycle (:attr:`_early_at`) when a command taken at ``now`` moves the head before the
        next deadline: a live value (at its time tag, if any), a timecode sample, a stream frame (at its play time).
        It runs no earlier than the slot's start (one cycle per period slot) nor ``WAKE_MIN_GAP`` periods after the
        last cycle, and only before ``last`` (later, the deadline's own cycle comes as soon)."""
        if not self.state.life.commanding:
            return
        due = float("inf")
        for cmd in cmds:
            if isinstance(cmd, Live):
                due = min(due, now if cmd.at is None else cmd.at)
            elif isinstance(cmd, Timecode):
                due = now
            elif isinstance(cmd, Stream) and len(cmd.times):
                due = min(due, float(cmd.times.min()) + self.params.cfg.runtime.stream_delay_s)
        period = self.params.period
        at = max(due, now, self._deadline - period, self._last_t + WAKE_MIN_GAP * period)
        if at < last:
            self._early_at = at if self._early_at is None else min(self._early_at, at)

    def _bus_inputs(self) -> tuple[BusInput, ...]:
        out = []
        for bus in self.buses:
            fb = bus.feedback()
            out.append(BusInput(bus.name, fb.state.value, fb.connected, fb.positions, fb.stamp, fb.faults,
                                  fb.connection, fb.attempts, fb.retry_at, fb.written))
        return tuple(out)

    def _drain(self, deadline: float) -> list[Command]:
        """The commands waiting on the command pipe; stream frames and live values tell the phase lock when they
        reached the daemon (the server's receipt stamp, the same monotonic clock; the take time when it is unknown),
        for the cycle due at ``deadline``. The take time is no steady measure of arrival: the loop watches the pipe
        between cycles only until ``COMMAND_MARGIN_S`` + spin before each one and not during a cycle's work, so a
        frame near the lock's set point was taken either at once or at the next cycle's start, two clusters a third
        of a period apart at 500 Hz, and the lock, which acts only on a tight cluster, never engaged."""
        taken = self.clock()
        cmds = self.commands.recv(MAX_COMMANDS_PER_CYCLE)
        for cmd in cmds:
            if isinstance(cmd, (Stream, Live, Timecode)):
                self.trace.taken(cmd.received, taken)
                if self.phase_lock is not None and not isinstance(cmd, Timecode):
                    self.phase_lock.arrival(self._lock_time(cmd, taken), deadline)
        return cmds

    def _lock_time(self, cmd: Stream | Live, taken: float) -> float:
        """When ``cmd`` counts as arrived for the phase lock: its receipt stamp (its take time when unknown); with
        wake on input (a slotted lock), when it is due, as its early cycle would run it (a live value's time tag, a
        stream frame's play time), if that is later."""
        t = taken if cmd.received is None else min(cmd.received, taken)
        if self.phase_lock is None or not self.phase_lock.slotted:
            return t
        if isinstance(cmd, Live):
            return t if cmd.at is None else max(t, cmd.at)
        if len(cmd.times):
            return max(t, float(cmd.times.min()) + self.params.cfg.runtime.stream_delay_s)
        return t

    def _estop_now(self) -> str | None:
        estop = None
        if self.estop.tripped():
            estop = self.estop.reason()
        if self._signal_estop is not None:
            estop, self._signal_estop = self._signal_estop, None
        return estop

    def _inputs(self, t: float) -> CycleInputs:
        buses = self._bus_inputs()
        cmds = self._drain(t)
        if self._carry:
            cmds, self._carry = self._carry + cmds, []
        results = []
        if self._tickets:
            for (i, ticket), op in list(self._tickets.items()):
                res = self.buses[i].result(ticket)
                if res is not None:
                    del self._tickets[i, ticket]
                    results.append((self.buses[i].name, op, res[0], res[1]))
        inputs = CycleInputs(t, buses, tuple(cmds), tuple(results), self._estop_now())
        if self.input_log is not None:
            self.input_log.append(inputs)
        return inputs

    def _write(self, out: CycleOutputs, t: float) -> None:
        """Post the commands (stamped with the cycle's time, which the drivers' rate guard measures against) and
        the lifecycle requests."""
        if self.output_log is not None:
            self.output_log.append(None if out.write is None else out.write.copy())
        if out.write is not None:
            q = out.write
            for bus, (_, idx) in zip(self.buses, self.params.buses, strict=True):
                bus.post(q[idx], t)
        for name, op in out.bus_requests:
            for i, bus in enumerate(self.buses):
                if bus.name == name:
                    self._tickets[i, bus.request(op)] = op

    def _outbox(self, out: CycleOutputs) -> None:
        if out.record is not None:
            self._send(L.RecordedRows(out.record))
        for token, body in out.replies:
            self._send(L.Reply(token, body))
        for event in out.events:
            self._send(L.Event(event))
        if out.telemetry is not None:
            self._send(L.StateSnapshot(out.telemetry))

    def _send_stats(self) -> None:
        s = self.stats
        k = min(s.n, s.window)
        lock = None
        if self.phase_lock is not None:
            err = self.phase_lock.last_error
            lock = L.PhaseLockReport(self.phase_lock.locked, None if err is None else err * 1e6)
        self._send(L.LoopStatistics(s.period, s.n, s.missed, s.skipped, s.lateness[:k].copy(), s.work[:k].copy(),
                                    s.periods[:k].copy(), lock, s.early))

    def _send(self, msg: L.FromLoop) -> None:
        try:
            L.send_to_server(self.sock, msg, zmq.NOBLOCK)
        except zmq.Again:
            pass  # the server is not keeping up: telemetry is dropped, the loop never waits
        except zmq.ZMQError as exc:
            log.debug("send to the server failed: %s", exc)


def _pin_cpu(cpu: int) -> str:
    """Pin the calling thread to ``cpu`` (-1: leave it); returns a note for the status line."""
    if cpu < 0 or not hasattr(os, "sched_setaffinity"):
        return ""
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError as exc:
        return f"; CPU pinning to {cpu} failed ({exc})"
    return f", pinned to CPU {cpu}"
