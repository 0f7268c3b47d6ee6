"""The loop side of one bus process: :class:`BusProxy` posts targets and takes feedback without ever waiting.

A :class:`BusProxy` spawns the bus process (``spawn`` start method, :func:`runtime.bus.process.main`), which runs the
bus's real driver. Targets go one way and feedback the other through one block of shared memory
(:mod:`runtime.bus.layout`): :meth:`BusProxy.post` and :meth:`BusProxy.feedback` take microseconds whatever the bus
does. A byte on a pipe wakes the bus process for new targets; lifecycle requests (enable, disable, reset) travel as
typed messages (:mod:`runtime.bus.messages`) over a control pipe and run between transactions.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import multiprocessing as mp
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from multiprocessing.shared_memory import SharedMemory

import numpy as np

import runtime.bus.layout as L
from drivers import errors as bus_errors
from drivers.base import LifecycleState, MotorConfig
from drivers.errors import BusInitError
from runtime.bus.config import BusProcessConfig, DriverOptions
from runtime.bus.layout import CONNECTION_STATES, ConnectionState, Faults
from runtime.bus.messages import BUS_OPS, BusOp, FromBusProcess, Opened, OpRequest, OpResult, StopRequest
from runtime.bus.process import main as bus_process_main

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BusFeedback:
    """A consistent snapshot of one bus as its process last published it (SI units, the proxy's actuator order)."""

    seq: int  # completed reads
    positions: np.ndarray  # NaN before the first read
    velocities: np.ndarray
    stamp: float  # time.monotonic() of the oldest motor sample in this read
    state: LifecycleState
    faults: Faults
    connected: bool  # process alive and bus open and reachable
    written: np.ndarray  # last targets written to the bus; after an enable, the positions it holds (NaN before any)
    write_stamp: float  # time.monotonic() of that write (0.0 before)
    io_us: float  # duration of the last write + read transaction in the bus process
    connection: ConnectionState = "closed"
    attempts: int = 0  # reconnect attempts since the connection was last lost
    retry_at: float = math.inf  # time.monotonic() of the next reconnect attempt (inf: none planned)


#: How often :meth:`BusProxy.feedback` asks whether the bus process lives (a system call, tens of µs in a control
#: cycle whose caches the other processes evicted); a dead process is noticed within this time.
ALIVE_CHECK_S = 0.005


class BusProxy:
    """The loop-side end of one bus running in its own process.

    ``post`` and ``feedback`` never block and never pickle; ``request``/``result`` carry lifecycle operations.
    ``realtime_priority`` asks for SCHED_FIFO in the bus process (normal priority by default), ``write_priority``
    for SCHED_FIFO within a CPU budget (:class:`runtime.bus.config.BusProcessConfig`);
    ``nice`` is added to its niceness; ``open_attempts`` retries opening on a driver error (emulated buses that share
    a loaded CPU can miss a reply window).
    """

    def __init__(
        self,
        driver: str,
        name: str,
        options: DriverOptions,
        motors: Sequence[MotorConfig],
        *,
        idle_hz: float = 100.0,
        realtime_priority: int | None = None,
        write_priority: int = 0,
        open_attempts: int = 1,
        nice: int = 0,
    ) -> None:
        self._config = BusProcessConfig(
            driver=driver, name=name, options=dict(options),
            motors=tuple(dataclasses.replace(m, options=dict(m.options)) for m in motors),
            idle_hz=float(idle_hz), realtime_priority=realtime_priority,
            write_priority=int(write_priority), open_attempts=max(1, int(open_attempts)),
            nice=int(nice), log_level=max(logging.getLogger().getEffectiveLevel(), logging.INFO),
        )
        self.name = name
        self.actuators: tuple[str, ...] = tuple(m.name for m in motors)
        self.motors: dict[str, MotorConfig] = {m.name: m for m in motors}
        n = len(self.actuators)
        self._layout = L.Layout(n)
        self._shm: SharedMemory | None = None
        self._views: L.Views | None = None
        self._proc: BaseProcess | None = None
        self._ctrl: Connection | None = None
        self._wake: Connection | None = None
        self._wake_fd = -1
        self._tickets = itertools.count(1)
        self._results: dict[int, tuple[bool, str]] = {}
        self._posted = 0
        self._fb_done = -1
        self._faults_version = -1.0
        self._faults: Faults = {}
        nan = np.full(n, np.nan)
        self._last = BusFeedback(0, nan, nan.copy(), 0.0, LifecycleState.UNCONFIGURED, {}, False, nan.copy(), 0.0,
                                 0.0)
        self._dead: BusFeedback | None = None
        self._alive_check_at = 0.0  # when feedback() next asks whether the bus process lives
        self._stopped = False

    # ------------------------------------------------------------------ lifecycle
    @property
    def pid(self) -> int | None:
        """Process id of the bus process (None before :meth:`start`)."""
        return None if self._proc is None else self._proc.pid

    @property
    def feedback_published(self) -> int:
        """How many feedback snapshots the bus process has published (0 before :meth:`start`)."""
        return 0 if self._views is None else int(self._views.counters[L.C_FB_DONE])

    def start(self, timeout_s: float = 30.0) -> None:
        """Spawn the bus process and open the bus (torque off); raises the driver's typed error on failure."""
        if self._proc is not None:
            raise RuntimeError(f"bus {self.name!r}: bus process already started")
        ctx = mp.get_context("spawn")
        self._shm = SharedMemory(create=True, size=self._layout.size)
        self._views = self._layout.views(self._shm.buf)
        self._layout.initialize(self._views)
        ctrl_parent, ctrl_child = ctx.Pipe(duplex=True)
        wake_r, wake_w = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=bus_process_main, args=(self._config, self._shm.name, ctrl_child, wake_r),
            name=f"likeness-bus-{self.name}", daemon=True,
        )
        self._proc.start()
        ctrl_child.close()
        wake_r.close()
        self._ctrl, self._wake = ctrl_parent, wake_w
        self._wake_fd = wake_w.fileno()
        os.set_blocking(self._wake_fd, False)
        opened = self._await_open(ctrl_parent, self._proc, timeout_s)
        if opened.error is None:
            self._stopped = False
            return
        self.stop(timeout_s=2.0)
        raise opened.error.rebuild(self.name)

    def _await_open(self, ctrl: Connection, proc: BaseProcess, timeout_s: float) -> Opened:
        """The bus process's :class:`Opened`; BusInitError (after stopping it) if it exits or stays silent."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or (not proc.is_alive() and not ctrl.poll(0)):
                code = proc.exitcode
                self.stop(timeout_s=2.0)
                raise BusInitError(f"bus {self.name!r}: opening timed out after {timeout_s:g} s" if left <= 0
                                   else f"bus {self.name!r}: bus process exited with code {code} while opening")
            if ctrl.poll(min(left, 0.1)):
                try:
                    msg: FromBusProcess = ctrl.recv()
                except EOFError:
                    continue
                if isinstance(msg, Opened):
                    return msg

    def stop(self, timeout_s: float = 5.0) -> None:
        """Torque off, close the bus, end the process (killed after ``timeout_s``) and free the shared block.

        Idempotent; never raises.
        """
        if self._stopped and self._proc is None:
            return
        self._stopped = True
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.is_alive() and self._ctrl is not None:
                with contextlib.suppress(OSError, ValueError):
                    self._ctrl.send(StopRequest())
                    self._wake_now()
            proc.join(timeout_s)
            if proc.is_alive():
                log.warning("bus %s: process did not stop in %.1f s; killing it", self.name, timeout_s)
                proc.kill()
                proc.join(2.0)
            with contextlib.suppress(ValueError):
                proc.close()
        for conn in (self._ctrl, self._wake):
            if conn is not None:
                with contextlib.suppress(OSError):
                    conn.close()
        self._ctrl = self._wake = None
        self._wake_fd = -1
        self._last = dataclasses.replace(self._dead or self._last, connected=False,
                                         state=LifecycleState.UNCONFIGURED, connection="closed", retry_at=math.inf)
        self._views = None
        if self._shm is not None:
            shm, self._shm = self._shm, None
            with contextlib.suppress(BufferError, FileNotFoundError):
                shm.close()
                shm.unlink()
        self._dead = None

    def kill(self) -> None:
        """Kill the bus process at once (no torque off): for tests of a crashed bus process."""
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2.0)
        self._alive_check_at = 0.0

    # ------------------------------------------------------------------ cyclic exchange (loop side)
    def post(self, targets: np.ndarray, stamp: float | None = None) -> None:
        """Hand the bus the latest SI position targets (``len(actuators)``, proxy order); never blocks.

        Only targets posted after an ``enable`` completes are written; a later post replaces one not yet written.
        ``stamp`` is when the targets were computed (default now): the driver's rate guard measures between the
        stamps of successive writes, so a late delivery is not mistaken for a fast move.
        """
        views = self._views
        if views is None:
            raise RuntimeError(f"bus {self.name!r}: post before start")
        if len(targets) != self._layout.n:
            raise ValueError(f"bus {self.name!r}: {len(targets)} targets for {self._layout.n} actuators "
                             f"({', '.join(self.actuators)})")
        c = views.counters
        k = self._posted + 1
        c[L.C_TG_BEGUN] = k
        buf = views.targets[k & 1]
        buf[0] = time.monotonic() if stamp is None else stamp
        buf[1:] = targets
        c[L.C_TG_DONE] = k
        self._posted = k
        self._wake_now()

    def _wake_now(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_fd, b"\x01")

    def feedback(self) -> BusFeedback:
        """The latest published feedback; a dead bus process shows ``connected=False`` and state FAULT."""
        views = self._views
        if views is None:
            return self._last
        if self._dead is not None:
            return self._dead
        c = views.counters
        done = int(c[L.C_FB_DONE])
        if done != self._fb_done:
            for _ in range(3):
                done = int(c[L.C_FB_DONE])
                snap = views.feedback[done & 1].copy()
                if int(c[L.C_FB_BEGUN]) < done + 2:
                    self._last = self._unpack(views, snap)
                    self._fb_done = done
                    break
        proc = self._proc
        if proc is None:
            return self._last
        now = time.monotonic()
        if now < self._alive_check_at:
            return self._last
        self._alive_check_at = now + ALIVE_CHECK_S
        if not proc.is_alive():
            last = self._last
            faults = dict(last.faults)
            faults.setdefault(self.name, (0, f"bus process exited (code {proc.exitcode})"))
            self._dead = dataclasses.replace(last, state=LifecycleState.FAULT, connected=False, faults=faults,
                                             connection="lost", retry_at=math.inf)
            log.error("bus %s: bus process died (exit code %s)", self.name, proc.exitcode)
            return self._dead
        return self._last

    def _unpack(self, views: L.Views, snap: np.ndarray) -> BusFeedback:
        n = self._layout.n
        h = L.N_HEADER
        head = snap[:h].tolist()  # the header as Python floats in one call
        version = head[L.H_FAULTS]
        if version != self._faults_version:
            got = L.read_faults(views)
            if got is not None:
                self._faults_version, self._faults = float(got[0]), got[1]
        return BusFeedback(
            seq=int(head[L.H_SEQ]), positions=snap[h:h + n], velocities=snap[h + n:h + 2 * n],
            stamp=head[L.H_STAMP], state=L.LIFECYCLE_STATES[int(head[L.H_STATE])], faults=self._faults,
            connected=bool(head[L.H_CONNECTED]), written=snap[h + 2 * n:h + 3 * n],
            write_stamp=head[L.H_WSTAMP] if math.isfinite(head[L.H_WSTAMP]) else 0.0,
            io_us=head[L.H_IO_US] if math.isfinite(head[L.H_IO_US]) else 0.0,
            connection=CONNECTION_STATES[int(head[L.H_CONNECTION])] if math.isfinite(head[L.H_CONNECTION])
            else "closed",
            attempts=int(head[L.H_ATTEMPTS]) if math.isfinite(head[L.H_ATTEMPTS]) else 0,
            retry_at=head[L.H_RETRY_AT] if not math.isnan(head[L.H_RETRY_AT]) else math.inf,
        )

    # ------------------------------------------------------------------ lifecycle requests (loop side)
    def request(self, op: str) -> int:
        """Ask for ``"enable"``, ``"disable"`` or ``"reset"`` (fault reset); returns a ticket for :meth:`result`."""
        checked = _bus_op(op)
        if checked is None:
            raise ValueError(f"bus {self.name!r}: unknown operation {op!r}; known: {', '.join(BUS_OPS)}")
        ticket = next(self._tickets)
        if self._ctrl is None or self._proc is None or not self._proc.is_alive():
            self._results[ticket] = (False, f"bus {self.name!r}: bus process is not running")
            return ticket
        try:
            self._ctrl.send(OpRequest(checked, ticket))
        except (OSError, ValueError) as exc:
            self._results[ticket] = (False, f"bus {self.name!r}: cannot reach the bus process ({exc})")
        self._wake_now()
        return ticket

    def result(self, ticket: int) -> tuple[bool, str] | None:
        """``(ok, error message)`` of a request, or None while it is pending (a dead process fails it)."""
        self._drain()
        out = self._results.pop(ticket, None)
        if out is None and (self._proc is None or not self._proc.is_alive()):
            self._drain()
            out = self._results.pop(ticket, None)
            if out is None:
                return False, f"bus {self.name!r}: bus process is not running"
        return out

    def call(self, op: str, timeout_s: float = 10.0) -> None:
        """Request ``op`` and wait for it (for start-up and tests, not for a control cycle); raises BusError."""
        ticket = self.request(op)
        deadline = time.monotonic() + timeout_s
        while (res := self.result(ticket)) is None:
            if time.monotonic() > deadline:
                raise bus_errors.BusTimeout(self.name, f"{op} did not complete in {timeout_s:g} s")
            time.sleep(0.002)
        if not res[0]:
            raise bus_errors.BusError(res[1])

    def _drain(self) -> None:
        conn = self._ctrl
        if conn is None:
            return
        with contextlib.suppress(EOFError, OSError):
            while conn.poll(0):
                msg: FromBusProcess = conn.recv()
                if isinstance(msg, OpResult):
                    self._results[msg.ticket] = (msg.ok, msg.message)


def _bus_op(op: str) -> BusOp | None:
    """``op`` as a :data:`BusOp`, or None if it names no operation."""
    for known in BUS_OPS:
        if op == known:
            return known
    return None
