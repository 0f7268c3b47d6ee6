"""A motor bus driven from its own thread: the control loop posts targets and reads the latest feedback, never
waiting for the bus (ros2_control's asynchronous components).

The loop-side calls (:meth:`post`, :meth:`feedback`, :meth:`request`, :meth:`result`) only swap references; the
driver's transactions, lifecycle transitions and errors all happen on the bus thread. Any exception from the driver
puts the bus in FAULT with the message; the thread lives on.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from drivers.base import LifecycleState, MotorBus

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BusFeedback:
    seq: int
    positions: np.ndarray
    velocities: np.ndarray
    stamp: float
    state: LifecycleState
    faults: dict[str, tuple[int, str]] = field(default_factory=dict)
    connected: bool = True
    written: np.ndarray | None = None
    write_stamp: float = 0.0
    io_us: float = 0.0


class ThreadBusLink:
    """One bus, its driver called from a dedicated thread."""

    def __init__(self, bus: MotorBus, idle_hz: float = 100.0) -> None:
        self.bus = bus
        self.name = bus.name
        self.actuators = tuple(bus.motors)
        n = len(self.actuators)
        self._idle = 1.0 / idle_hz
        self._targets: tuple[np.ndarray, float] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._requests: list[tuple[int, str]] = []
        self._results: dict[int, tuple[bool, str]] = {}
        self._tickets = itertools.count(1)
        nan = np.full(n, np.nan)
        self._fb = BusFeedback(0, nan, nan.copy(), -np.inf, LifecycleState.UNCONFIGURED, connected=False)
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ loop side (non-blocking)
    def post(self, targets: np.ndarray, stamp: float | None = None) -> None:
        self._targets = (targets, time.monotonic() if stamp is None else stamp)
        self._wake.set()

    def feedback(self) -> BusFeedback:
        return self._fb

    def request(self, op: str) -> int:
        ticket = next(self._tickets)
        self._requests.append((ticket, op))
        self._wake.set()
        return ticket

    def result(self, ticket: int) -> tuple[bool, str] | None:
        return self._results.pop(ticket, None)

    # ------------------------------------------------------------------ lifecycle (caller's thread)
    def start(self, timeout_s: float = 30.0) -> None:
        if self.bus.state is LifecycleState.UNCONFIGURED:
            self.bus.open()
        self._publish(time.monotonic())
        self._thread = threading.Thread(target=self._run, name=f"bus-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        try:
            self.bus.close()
        except Exception:
            log.exception("bus %s: close failed", self.name)

    # ------------------------------------------------------------------ bus thread
    def _run(self) -> None:
        written = None
        write_stamp = 0.0
        while not self._stop.is_set():
            self._wake.wait(self._idle)
            self._wake.clear()
            while self._requests:
                ticket, op = self._requests.pop(0)
                self._results[ticket] = self._do(op)
            t0 = time.perf_counter()
            posted, self._targets = self._targets, None
            try:
                if posted is not None and self.bus.state is LifecycleState.ACTIVE:
                    q, stamp = posted
                    self.bus.write(dict(zip(self.actuators, q.tolist(), strict=True)), stamp)
                    written, write_stamp = q, time.monotonic()
                self._publish(time.monotonic(), written, write_stamp, (time.perf_counter() - t0) * 1e6)
            except Exception as exc:
                self._error(exc)

    def _do(self, op: str) -> tuple[bool, str]:
        bus = self.bus
        try:
            if op == "enable":
                if bus.state is not LifecycleState.ACTIVE:
                    bus.enable()
            elif op == "disable":
                if bus.state is LifecycleState.ACTIVE:
                    bus.disable()
            elif op == "reset":
                if bus.state is LifecycleState.ACTIVE:
                    bus.disable()
                if bus.state is LifecycleState.FAULT:
                    bus.reset_fault()
            else:
                return False, f"unknown request {op!r}"
            self._targets = None
            self._publish(time.monotonic())
            return True, ""
        except Exception as exc:
            self._publish(time.monotonic())
            return False, f"{type(exc).__name__}: {exc}"

    def _error(self, exc: BaseException) -> None:
        if self.bus.state is not LifecycleState.FAULT:
            self.bus.mark_fault(self.name, 0xFF01, f"{type(exc).__name__}: {exc}")
        prev = self._fb
        self._fb = BusFeedback(prev.seq + 1, prev.positions, prev.velocities, prev.stamp, self.bus.state,
                               self.bus.faults(), True, prev.written, prev.write_stamp, prev.io_us)

    def _publish(self, now: float, written: np.ndarray | None = None, write_stamp: float = 0.0,
                 io_us: float = 0.0) -> None:
        bus = self.bus
        if bus.state is LifecycleState.UNCONFIGURED:
            return
        states = bus.read()
        pos = np.array([states[n].position for n in self.actuators])
        vel = np.array([states[n].velocity for n in self.actuators])
        stamp = min(states[n].timestamp for n in self.actuators)
        prev = self._fb
        faults = bus.faults()
        self._fb = BusFeedback(prev.seq + 1, pos, vel, stamp, bus.state, faults if faults else {}, True,
                               written if written is not None else prev.written,
                               write_stamp or prev.write_stamp, io_us)
