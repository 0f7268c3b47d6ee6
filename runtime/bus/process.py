"""The bus process: one motor bus's real driver, served to the loop side through shared memory and a control pipe.

:func:`main` is the process's entry point. :class:`BusServer` writes the latest posted targets and reads on wake-up
or at ``idle_hz``, publishes feedback (:mod:`runtime.bus.layout`), and carries out lifecycle requests between
transactions. Any driver error puts the bus in FAULT with its message; the process lives on.

Connection loss: an I/O error that means the transport is gone (``BrokenPipeError`` on a socketcand connection, a
serial port or pseudo-terminal that vanished: :class:`drivers.errors.BusConnectionLost`) puts the bus in FAULT and
its connection state to ``lost``; the process then tries to open the bus again in the background, with exponential
backoff (``reconnect_base_s`` doubling up to ``reconnect_max_s``), publishing ``reconnecting`` during an attempt and
the attempt count. A ``reset`` while the bus is unreachable makes one attempt at once and fails if it fails.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import select
import signal
import sys
import time
from collections.abc import Mapping
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory

import numpy as np

import runtime.bus.layout as L
from drivers import errors as bus_errors
from drivers.base import LifecycleState, MotorState
from drivers.errors import BusConnectionLost
from runtime.bus.config import BusProcessConfig
from runtime.bus.layout import ConnectionState, Faults
from runtime.bus.messages import BusOp, ErrorInfo, Opened, OpRequest, OpResult, ToBusProcess
from runtime.rtbudget import RealtimeBudget

log = logging.getLogger(__name__)

#: ``sys.setswitchinterval`` in the bus process (s): other threads yield the GIL to a write this soon.
SWITCH_INTERVAL_S = 0.0002
#: Share of the realtime budget reads may use; the rest is kept for writes (:meth:`RealtimeBudget.keep_for_urgent`).
#: All of it: at :data:`BUS_SHARE` a write and a read fit the budget (the sample head's CAN bus at 500 Hz uses about
#: half of it), and dropping the process to normal scheduling for a read left its thread, holding the interpreter
#: lock, preempted by the emulators, so the driver's receive thread waited behind it.
READ_SHARE = 1.0
#: Share of a core the bus process may take at realtime priority (all its threads together, over the budget's
#: window): the sample head's seven CANopen drives at 500 Hz take about 35 % (writes, reads and the driver's receive
#: thread), so a share of 20 % ran out in every window and the rest of it was written behind the emulators; a
#: driver that spins still gives a core back after this much of each window.
BUS_SHARE = 0.6
#: A counter value no post reaches: nothing is written before the next enable.
_NEVER = 1 << 62


class BusServer:
    """Runs in the bus process: transactions on wake-up or at the idle rate, lifecycle requests in between."""

    def __init__(self, cfg: BusProcessConfig, shm: SharedMemory, ctrl: Connection, wake: Connection) -> None:
        from drivers.registry import create_bus

        self.cfg = cfg
        self.ctrl = ctrl
        self.wake_fd = wake.fileno()
        os.set_blocking(self.wake_fd, False)
        self.names = [m.name for m in cfg.motors]
        self.views: L.Views | None = L.Layout(len(cfg.motors)).views(shm.buf)
        self.bus = create_bus(cfg.driver, cfg.name, cfg.options, cfg.motors)
        self.connected = False
        self.seq = 0
        self.written = np.full(len(cfg.motors), np.nan)
        self.write_stamp = 0.0
        self.io_us = 0.0
        self.written_k = 0
        self.enabled_k = _NEVER
        self.faults_seen: Faults = {}
        self.faults_version = 0
        self.last_error = ""
        self.connection: ConnectionState = "closed"
        self.attempts = 0
        self.retry_at = math.inf
        # realtime within a CPU budget (see BusProcessConfig.write_priority)
        self.budget = RealtimeBudget(cfg.write_priority if cfg.realtime_priority is None else 0, share=BUS_SHARE,
                                     whole_process=True)
        self.reconnect_error = ""
        self.parent = os.getppid()

    @property
    def v(self) -> L.Views:
        """The shared block's views (gone once the process is leaving)."""
        if self.views is None:
            raise RuntimeError(f"bus {self.cfg.name}: shared block released")
        return self.views

    # -------------------------------------------------------------- publication
    def publish(self, states: Mapping[str, MotorState] | None) -> None:
        """Publish a feedback snapshot: ``states`` from a read, or (None) the previous one with fresh status."""
        v = self.v
        c = v.counters
        k = int(c[L.C_FB_DONE]) + 1
        faults = self.bus.faults()
        if faults != self.faults_seen:
            self.faults_version += 1
            L.write_faults(v, faults, self.faults_version)
            self.faults_seen = dict(faults)
        c[L.C_FB_BEGUN] = k
        buf = v.feedback[k & 1]
        n = len(self.names)
        h = L.N_HEADER
        if states is not None:
            self.seq += 1
            buf[h:h + n] = [states[m].position for m in self.names]
            buf[h + n:h + 2 * n] = [states[m].velocity for m in self.names]
            buf[L.H_STAMP] = min(states[m].timestamp for m in self.names)
        else:
            buf[:] = v.feedback[(k - 1) & 1]
        buf[L.H_SEQ] = self.seq
        buf[h + 2 * n:h + 3 * n] = self.written
        buf[L.H_WSTAMP] = self.write_stamp
        buf[L.H_IO_US] = self.io_us
        buf[L.H_STATE] = L.LIFECYCLE_CODE[self.bus.state]
        buf[L.H_CONNECTED] = 1.0 if self.connected and self.bus.state is not LifecycleState.UNCONFIGURED else 0.0
        buf[L.H_FAULTS] = self.faults_version
        buf[L.H_CONNECTION] = L.CONNECTION_CODE[self.connection]
        buf[L.H_ATTEMPTS] = self.attempts
        buf[L.H_RETRY_AT] = self.retry_at
        c[L.C_FB_DONE] = k

    def latest_targets(self) -> tuple[int, np.ndarray | None]:
        """(post counter, [stamp, targets...]) of the latest consistent post, or (last written, None)."""
        v = self.v
        c = v.counters
        for _ in range(5):
            k = int(c[L.C_TG_DONE])
            if k == 0:
                return 0, None
            snap = v.targets[k & 1].copy()
            if int(c[L.C_TG_BEGUN]) < k + 2:
                return k, snap
        return self.written_k, None

    def has_fresh_targets(self) -> bool:
        """Whether the bus is active and targets were posted since the last write."""
        return self.bus.state is LifecycleState.ACTIVE and int(self.v.counters[L.C_TG_DONE]) != self.written_k

    # -------------------------------------------------------------- transactions
    def transaction(self) -> None:
        """Write the latest targets (when active and new), read, publish; a driver error faults the bus."""
        t0 = time.monotonic()
        states = None
        if not self.connected:  # nothing to talk to until a reconnect attempt succeeds
            self.publish(None)
            return
        try:
            k = int(self.v.counters[L.C_TG_DONE])
            if k != self.written_k and k > self.enabled_k and self.bus.state is LifecycleState.ACTIVE:
                k, snap = self.latest_targets()
                if snap is not None:
                    self.written_k = k
                    targets = snap[1:]
                    # rate check against the loop's own timing: a delay in this process must not fault the bus
                    self.bus.write(dict(zip(self.names, targets.tolist(), strict=True)), stamp=float(snap[0]))
                    self.written = targets
                    self.write_stamp = time.monotonic()
            # The write is urgent, the read less so: past READ_SHARE of the window's realtime budget, reads run at
            # normal scheduling and the rest is kept for writes.
            self.budget.keep_for_urgent(READ_SHARE)
            if self.bus.state is not LifecycleState.UNCONFIGURED:
                states = self.bus.read()
        except Exception as exc:
            self.fail(exc)
        self.io_us = (time.monotonic() - t0) * 1e6
        self.publish(states)

    def fail(self, exc: BaseException) -> None:
        """A driver error during I/O: the bus goes to FAULT with the message; a lost connection clears ``connected``
        and starts the reconnect attempts."""
        message = f"{type(exc).__name__}: {exc}"
        if self.connected and _connection_lost(exc):
            self.lose(message)
        device = getattr(exc, "device", None) or self.bus.name
        code = getattr(exc, "code", 0) if isinstance(getattr(exc, "code", 0), int) else 0
        if message != self.last_error:
            log.error("bus %s: %s", self.bus.name, message)
            self.last_error = message
        with contextlib.suppress(Exception):
            if self.bus.state is not LifecycleState.FAULT or str(device) not in self.bus.faults():
                self.bus.mark_fault(str(device), int(code), message)

    # -------------------------------------------------------------- connection
    def lose(self, why: str) -> None:
        """The transport is gone: stop all I/O and plan the first reconnect attempt."""
        self.connected = False
        self.connection = "lost"
        self.attempts = 0
        self.retry_at = time.monotonic() + self.cfg.reconnect_base_s
        log.error("bus %s: connection lost (%s); reopening in the background", self.bus.name, why)

    def reconnect(self) -> bool:
        """One attempt to open the bus again (closing what is left of it first); on failure the next attempt is
        planned after an exponentially growing wait. True once the bus is open (inactive, torque off)."""
        self.attempts += 1
        self.connection = "reconnecting"
        self.retry_at = math.inf
        self.publish(None)
        with contextlib.suppress(Exception):
            self.bus.close()
        try:
            self.bus.open()
        except Exception as exc:
            delay = min(self.cfg.reconnect_max_s, self.cfg.reconnect_base_s * 2.0 ** self.attempts)
            self.retry_at = time.monotonic() + delay
            self.connection = "lost"
            self.reconnect_error = f"{type(exc).__name__}: {exc}"
            log.warning("bus %s: reconnect attempt %d failed (%s); next in %.2g s", self.bus.name, self.attempts,
                        self.reconnect_error, delay)
            with contextlib.suppress(Exception):
                self.bus.close()
            self.publish(None)
            return False
        self.connected = True
        self.connection = "connected"
        self.retry_at = math.inf
        self.last_error = self.reconnect_error = ""
        self.written_k = self.enabled_k = _NEVER  # nothing is written before the next enable
        log.warning("bus %s: reopened after %d reconnect attempt(s); send reset, then enable", self.bus.name,
                    self.attempts)
        self.publish(None)
        return True

    def open(self) -> None:
        """Open the bus (torque off), retrying up to ``open_attempts`` times on a driver error."""
        attempts = self.cfg.open_attempts
        for attempt in range(1, attempts + 1):
            try:
                self.bus.open()
                self.connected = True
                self.connection = "connected"
                return
            except bus_errors.ConfigError:
                raise
            except Exception as exc:
                if attempt == attempts:
                    raise
                log.warning("bus %s: open attempt %d failed (%s); retrying", self.bus.name, attempt, exc)
                with contextlib.suppress(Exception):
                    self.bus.close()

    # -------------------------------------------------------------- lifecycle requests
    def lifecycle(self, op: BusOp) -> None:
        """Carry out one lifecycle operation; raises the driver's error (or BusConnectionLost) if it fails."""
        bus = self.bus
        if op == "enable":
            if bus.state is not LifecycleState.ACTIVE:
                bus.enable()
            self.enabled_k = int(self.v.counters[L.C_TG_DONE])
            self.written_k = self.enabled_k
            # what the motors hold now is the last command: the loop starts commanding from it (the driver measures
            # the first target's step against it; the measured positions may have moved on since)
            held = bus.last_commands()
            self.written = np.array([held.get(name, np.nan) for name in self.names])  # (nothing written: no stamp)
        elif op == "disable":
            if bus.state is LifecycleState.ACTIVE:
                bus.disable()
        elif op == "reset":
            self.reset()

    def reset(self) -> None:
        """Clear a fault; on a bus that is unreachable (or never opened), make one reconnect attempt at once."""
        bus = self.bus
        if not self.connected or bus.state is LifecycleState.UNCONFIGURED:
            if not self.reconnect():
                raise BusConnectionLost(
                    f"bus {bus.name!r} is still unreachable ({self.reconnect_error}); reconnect attempt "
                    f"{self.attempts}, next in {max(0.0, self.retry_at - time.monotonic()):.2g} s")
        elif bus.state is LifecycleState.FAULT:
            bus.reset_fault()
            self.last_error = ""

    def handle_requests(self) -> bool:
        """Carry out queued lifecycle requests; False when asked to stop."""
        while self.ctrl.poll(0):
            try:
                msg: ToBusProcess = self.ctrl.recv()
            except (EOFError, OSError):
                return False
            if not isinstance(msg, OpRequest):
                return False
            try:
                self.lifecycle(msg.op)
                reply = OpResult(msg.ticket, True)
            except Exception as exc:
                if not isinstance(exc, bus_errors.LifecycleError) and self.connected:
                    self.fail(exc)
                reply = OpResult(msg.ticket, False, f"{type(exc).__name__}: {exc}")
            self.publish(None)
            try:
                self.ctrl.send(reply)
            except (OSError, ValueError):
                return False
        return True

    def serve(self) -> None:
        """Until asked to stop (or the parent is gone): wait for a wake-up, a request, the idle deadline or the next
        reconnect attempt, and act on it."""
        period = 1.0 / self.cfg.idle_hz
        poller = select.poll()
        poller.register(self.wake_fd, select.POLLIN)
        poller.register(self.ctrl.fileno(), select.POLLIN)
        next_idle = time.monotonic()
        log.info("bus %s: %s within a CPU budget", self.bus.name, self.budget.enter())
        while True:
            self.budget.rearm()
            wait_ms = max(0.0, (min(next_idle, self.retry_at) - time.monotonic()) * 1e3)
            events = poller.poll(math.ceil(wait_ms)) if wait_ms > 0 else []
            woken = False
            for fd, _ in events:
                if fd == self.wake_fd:
                    with contextlib.suppress(BlockingIOError, OSError):
                        os.read(self.wake_fd, 4096)
                    woken = True
            if not self.handle_requests():
                return
            if os.getppid() != self.parent:
                log.error("bus %s: parent process gone; closing the bus", self.bus.name)
                return
            if not self.connected and time.monotonic() >= self.retry_at:
                self.reconnect()
            now = time.monotonic()
            if (woken and self.has_fresh_targets()) or now >= next_idle:
                self.transaction()
                self.budget.spent()  # over its CPU budget: normal scheduling for the rest of the window
                next_idle = max(next_idle + period, time.monotonic()) if now >= next_idle else next_idle

    def close(self) -> None:
        """Close the bus (torque off), publish the closed state and let go of the shared block; never raises."""
        with contextlib.suppress(Exception):
            self.bus.close()
        self.connected = False
        with contextlib.suppress(Exception):
            self.publish(None)
        self.views = None


def _connection_lost(exc: BaseException) -> bool:
    """Whether a driver error means the transport is gone (rather than a device fault or a missed answer): an
    ``OSError``, the drivers' ``BusConnectionLost``, or an error of the transport libraries, pyserial's and
    python-can's, and ``termios.error`` (not an ``OSError``), which pyserial raises when a pseudo-terminal or adapter
    vanishes while it sets the line up."""
    return isinstance(exc, OSError | BusConnectionLost) or type(exc).__module__.startswith(("serial", "can.",
                                                                                             "termios"))


def _setup_process(cfg: BusProcessConfig) -> None:
    """Signals, logging, niceness and (when asked) realtime priority of a fresh bus process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops this process; Ctrl-C reaches the parent

    def _terminate(*_: object) -> None:
        raise SystemExit(0)  # SIGTERM (e.g. multiprocessing's exit handler): leave through the torque-off below

    signal.signal(signal.SIGTERM, _terminate)
    # The driver's own threads (python-can's notifier parsing every received frame, heartbeat monitors) must hand the
    # GIL back within a fraction of a control period when new targets wake this process: at the default 5 ms a
    # write waited up to a whole switch interval behind them (the bus-write stage's p99 at 500 Hz).
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    logging.basicConfig(level=cfg.log_level, format=f"%(asctime)s bus {cfg.name} %(levelname)s %(message)s")
    if cfg.nice:
        with contextlib.suppress(OSError):
            os.nice(cfg.nice)
    if cfg.realtime_priority is not None:
        from runtime.loop import try_realtime

        ok, message = try_realtime(cfg.realtime_priority)
        (log.info if ok else log.warning)("bus %s: %s", cfg.name, message)


def main(cfg: BusProcessConfig, shm_name: str, ctrl: Connection, wake: Connection) -> None:
    """Entry point of the bus process: open the bus, say so on ``ctrl``, serve until stopped, close the bus."""
    _setup_process(cfg)
    shm = SharedMemory(name=shm_name)
    server: BusServer | None = None
    try:
        try:
            server = BusServer(cfg, shm, ctrl, wake)
            server.open()
        except Exception as exc:
            with contextlib.suppress(OSError, ValueError):
                ctrl.send(Opened(ErrorInfo.describe(exc)))
            return
        server.publish(None)
        server.transaction()
        ctrl.send(Opened())
        server.serve()
    finally:
        if server is not None:
            server.close()
        with contextlib.suppress(BufferError):
            shm.close()
