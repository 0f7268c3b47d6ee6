"""Each motor bus in a process of its own, reached from the control loop without blocking.

A :class:`BusLink` spawns a child process (``spawn`` start method) that runs the bus's real driver
(:func:`drivers.registry.create_bus`). The loop's process and the bus process share one block of
:mod:`multiprocessing.shared_memory`: targets go one way and feedback the other, each through a double buffer guarded
by a pair of counters (the writer bumps ``begun``, writes the buffer of that parity, then sets ``done``; a reader
copies the buffer of ``done``'s parity and keeps the copy if ``begun`` has not moved two further). Nothing is pickled
per cycle and no lock is shared with the loop: :meth:`BusLink.post` and :meth:`BusLink.feedback` take microseconds
whatever the bus does. A byte on a pipe wakes the bus process for new targets; without them it still reads at
``idle_hz``. Lifecycle requests (enable, disable, reset) travel over a pipe and run between transactions.

Connection loss: an I/O error that means the transport is gone (``BrokenPipeError`` on a socketcand connection, a
serial port or pseudo-terminal that vanished: :class:`drivers.errors.BusConnectionLost`) puts the bus in FAULT and
its link state to ``lost``; the bus process then tries to open the bus again in the background, with exponential
backoff (``reconnect_base_s`` doubling up to ``reconnect_max_s``), publishing ``reconnecting`` during an attempt and
the attempt count. A ``reset`` while the bus is unreachable makes one attempt at once and fails if it fails.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import logging
import math
import multiprocessing as mp
import os
import select
import signal
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from drivers import errors as bus_errors
from drivers.base import LifecycleState, MotorConfig
from drivers.errors import BusConnectionLost, BusInitError

log = logging.getLogger(__name__)

_STATES: tuple[LifecycleState, ...] = tuple(LifecycleState)
_STATE_CODE = {s: i for i, s in enumerate(_STATES)}
OPS = ("enable", "disable", "reset")
#: Connection states of a bus as its process reports them: not opened yet or stopped, open and reachable, lost (waiting
#: for the next reconnect attempt), an attempt in progress.
LINK_STATES = ("closed", "connected", "lost", "reconnecting")
_LINK_CODE = {s: i for i, s in enumerate(LINK_STATES)}

# counters (int64): feedback begun/done, targets begun/done, faults begun/done
_C_FB_BEGUN, _C_FB_DONE, _C_TG_BEGUN, _C_TG_DONE, _C_FA_BEGUN, _C_FA_DONE = range(6)
_N_COUNTERS = 8
# feedback header (float64), then positions, velocities, written (n each)
_H_SEQ, _H_STAMP, _H_WSTAMP, _H_IO_US, _H_STATE, _H_CONNECTED, _H_FAULTS, _H_LINK, _H_ATTEMPTS, _H_RETRY_AT = range(10)
_N_HEADER = 10
_FAULT_BYTES = 8192


@dataclass(frozen=True, slots=True)
class BusFeedback:
    """A consistent snapshot of one bus as its process last published it (SI units, actuator order of the link)."""

    seq: int  # completed reads
    positions: np.ndarray  # NaN before the first read
    velocities: np.ndarray
    stamp: float  # time.monotonic() of the oldest motor sample in this read
    state: LifecycleState
    faults: dict[str, tuple[int, str]]
    connected: bool  # process alive and bus open and reachable
    written: np.ndarray  # last targets written to the bus (NaN before the first write)
    write_stamp: float  # time.monotonic() of that write (0.0 before)
    io_us: float  # duration of the last write + read transaction in the bus process
    link: str = "closed"  # one of LINK_STATES
    attempts: int = 0  # reconnect attempts since the connection was last lost
    retry_at: float = math.inf  # time.monotonic() of the next reconnect attempt (inf: none planned)


class _Layout:
    """Offsets of the shared block for ``n`` actuators, and numpy views onto it."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.fb_len = _N_HEADER + 3 * n
        self.tg_len = 1 + n
        self.off_fb = _N_COUNTERS * 8
        self.off_tg = self.off_fb + 2 * self.fb_len * 8
        self.off_fa = self.off_tg + 2 * self.tg_len * 8
        self.size = self.off_fa + _FAULT_BYTES

    def views(self, buf: Any) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray],
                                       np.ndarray]:
        c = np.ndarray((_N_COUNTERS,), np.int64, buf, 0)
        fb = tuple(np.ndarray((self.fb_len,), np.float64, buf, self.off_fb + i * self.fb_len * 8) for i in (0, 1))
        tg = tuple(np.ndarray((self.tg_len,), np.float64, buf, self.off_tg + i * self.tg_len * 8) for i in (0, 1))
        fa = np.ndarray((_FAULT_BYTES,), np.uint8, buf, self.off_fa)
        return c, fb, tg, fa  # type: ignore[return-value]


@dataclass(frozen=True)
class BusProcessConfig:
    """What the bus process needs: the driver, its options and motors, and its timing."""

    driver: str
    name: str
    options: dict[str, Any]
    motors: tuple[dict[str, Any], ...]
    idle_hz: float = 100.0
    realtime_priority: int | None = None
    open_attempts: int = 1
    nice: int = 0
    log_level: int = logging.WARNING  # the daemon's: the drivers' libraries chatter at INFO
    reconnect_base_s: float = 0.25  # first reconnect attempt this long after a loss, then doubling
    reconnect_max_s: float = 4.0  # longest wait between two reconnect attempts


class BusLink:
    """The loop-side end of one bus running in its own process.

    ``post`` and ``feedback`` never block and never pickle; ``request``/``result`` carry lifecycle operations.
    ``realtime_priority`` asks for SCHED_FIFO in the bus process (normal priority by default); ``nice`` is added to
    its niceness; ``open_attempts`` retries opening on a driver error (emulated buses that share a loaded CPU can miss
    a reply window).
    """

    def __init__(
        self,
        driver: str,
        name: str,
        options: Mapping[str, Any],
        motors: Sequence[MotorConfig],
        *,
        idle_hz: float = 100.0,
        realtime_priority: int | None = None,
        open_attempts: int = 1,
        nice: int = 0,
    ) -> None:
        if not motors:
            raise ValueError(f"bus {name!r}: a bus link needs at least one motor")
        if not (math.isfinite(idle_hz) and idle_hz > 0):
            raise ValueError(f"bus {name!r}: idle_hz must be a positive number, got {idle_hz!r}")
        if realtime_priority is not None and not 1 <= realtime_priority <= 99:
            raise ValueError(f"bus {name!r}: realtime_priority must be 1..99, got {realtime_priority!r}")
        self.name = name
        self.actuators: tuple[str, ...] = tuple(m.name for m in motors)
        self.motors: dict[str, MotorConfig] = {m.name: m for m in motors}
        self._config = BusProcessConfig(
            driver=driver, name=name, options=dict(options),
            motors=tuple(dataclasses.asdict(m) | {"options": dict(m.options)} for m in motors),
            idle_hz=float(idle_hz), realtime_priority=realtime_priority, open_attempts=max(1, int(open_attempts)),
            nice=int(nice), log_level=max(logging.getLogger().getEffectiveLevel(), logging.INFO),
        )
        n = len(self.actuators)
        self._layout = _Layout(n)
        self._shm: SharedMemory | None = None
        self._proc: Any = None
        self._ctrl: Connection | None = None
        self._wake: Connection | None = None
        self._wake_fd = -1
        self._tickets = itertools.count(1)
        self._results: dict[int, tuple[bool, str]] = {}
        self._posted = 0
        self._fb_done = -1
        self._faults_version = -1.0
        self._faults: dict[str, tuple[int, str]] = {}
        nan = np.full(n, np.nan)
        self._last = BusFeedback(0, nan, nan.copy(), 0.0, LifecycleState.UNCONFIGURED, {}, False, nan.copy(), 0.0,
                                 0.0)
        self._dead: BusFeedback | None = None
        self._stopped = False

    # ------------------------------------------------------------------ lifecycle
    @property
    def pid(self) -> int | None:
        """Process id of the bus process (None before :meth:`start`)."""
        return None if self._proc is None else self._proc.pid

    def start(self, timeout_s: float = 30.0) -> None:
        """Spawn the bus process and open the bus (torque off); raises the driver's typed error on failure."""
        if self._proc is not None:
            raise RuntimeError(f"bus {self.name!r}: link already started")
        ctx = mp.get_context("spawn")
        self._shm = SharedMemory(create=True, size=self._layout.size)
        c, fb, tg, _ = self._layout.views(self._shm.buf)
        c[:] = 0
        for buf in fb:
            buf[:] = np.nan
            buf[_H_SEQ] = 0
            buf[_H_STATE] = _STATE_CODE[LifecycleState.UNCONFIGURED]
            buf[_H_CONNECTED] = 0
            buf[_H_FAULTS] = 0
            buf[_H_LINK] = _LINK_CODE["closed"]
            buf[_H_ATTEMPTS] = 0
            buf[_H_RETRY_AT] = math.inf
        for buf in tg:
            buf[:] = np.nan
        self._c, self._fb, self._tg = c, fb, tg
        ctrl_parent, ctrl_child = ctx.Pipe(duplex=True)
        wake_r, wake_w = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_bus_main, args=(self._config, self._shm.name, ctrl_child, wake_r),
            name=f"likeness-bus-{self.name}", daemon=True,
        )
        self._proc.start()
        ctrl_child.close()
        wake_r.close()
        self._ctrl, self._wake = ctrl_parent, wake_w
        self._wake_fd = wake_w.fileno()
        os.set_blocking(self._wake_fd, False)
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or (not self._proc.is_alive() and not ctrl_parent.poll(0)):
                why = "timed out" if left <= 0 else f"bus process exited with code {self._proc.exitcode}"
                self.stop(timeout_s=2.0)
                raise BusInitError(f"bus {self.name!r}: opening {why} after {timeout_s:g} s"
                                   if left <= 0 else f"bus {self.name!r}: {why} while opening")
            if ctrl_parent.poll(min(left, 0.1)):
                try:
                    msg = ctrl_parent.recv()
                except EOFError:
                    continue
                if msg[0] != "open":
                    continue
                if msg[1]:
                    self._stopped = False
                    return
                self.stop(timeout_s=2.0)
                raise _recreate(msg[2], self.name)

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
                    self._ctrl.send(("stop", 0))
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
                                         state=LifecycleState.UNCONFIGURED, link="closed", retry_at=math.inf)
        if self._shm is not None:
            self._c = self._fb = self._tg = None  # type: ignore[assignment]
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

    # ------------------------------------------------------------------ cyclic exchange (loop side)
    def post(self, targets: np.ndarray, stamp: float | None = None) -> None:
        """Hand the bus the latest SI position targets (``len(actuators)``, link order); never blocks.

        Only targets posted after an ``enable`` completes are written; a later post replaces one not yet written.
        ``stamp`` is when the targets were computed (default now): the driver's rate guard measures between the
        stamps of successive writes, so a late delivery is not mistaken for a fast move.
        """
        c = self._c if self._shm is not None else None
        if c is None:
            raise RuntimeError(f"bus {self.name!r}: post before start")
        if len(targets) != self._layout.n:
            raise ValueError(f"bus {self.name!r}: {len(targets)} targets for {self._layout.n} actuators "
                             f"({', '.join(self.actuators)})")
        k = self._posted + 1
        c[_C_TG_BEGUN] = k
        buf = self._tg[k & 1]
        buf[0] = time.monotonic() if stamp is None else stamp
        buf[1:] = targets
        c[_C_TG_DONE] = k
        self._posted = k
        self._wake_now()

    def _wake_now(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_fd, b"\x01")

    def feedback(self) -> BusFeedback:
        """The latest published feedback; a dead bus process shows ``connected=False`` and state FAULT."""
        if self._shm is None:
            return self._last
        if self._dead is not None:
            return self._dead
        c = self._c
        done = int(c[_C_FB_DONE])
        if done != self._fb_done:
            for _ in range(3):
                done = int(c[_C_FB_DONE])
                snap = self._fb[done & 1].copy()
                if int(c[_C_FB_BEGUN]) < done + 2:
                    self._last = self._unpack(snap)
                    self._fb_done = done
                    break
        proc = self._proc
        if proc is not None and not proc.is_alive():
            last = self._last
            faults = dict(last.faults)
            faults.setdefault(self.name, (0, f"bus process exited (code {proc.exitcode})"))
            self._dead = dataclasses.replace(last, state=LifecycleState.FAULT, connected=False, faults=faults,
                                             link="lost", retry_at=math.inf)
            log.error("bus %s: bus process died (exit code %s)", self.name, proc.exitcode)
            return self._dead
        return self._last

    def _unpack(self, snap: np.ndarray) -> BusFeedback:
        n = self._layout.n
        h = _N_HEADER
        version = snap[_H_FAULTS]
        if version != self._faults_version:
            self._read_faults(version)
        return BusFeedback(
            seq=int(snap[_H_SEQ]), positions=snap[h:h + n], velocities=snap[h + n:h + 2 * n],
            stamp=float(snap[_H_STAMP]), state=_STATES[int(snap[_H_STATE])], faults=self._faults,
            connected=bool(snap[_H_CONNECTED]), written=snap[h + 2 * n:h + 3 * n],
            write_stamp=float(snap[_H_WSTAMP]) if math.isfinite(snap[_H_WSTAMP]) else 0.0,
            io_us=float(snap[_H_IO_US]) if math.isfinite(snap[_H_IO_US]) else 0.0,
            link=LINK_STATES[int(snap[_H_LINK])] if math.isfinite(snap[_H_LINK]) else "closed",
            attempts=int(snap[_H_ATTEMPTS]) if math.isfinite(snap[_H_ATTEMPTS]) else 0,
            retry_at=float(snap[_H_RETRY_AT]) if not math.isnan(snap[_H_RETRY_AT]) else math.inf,
        )

    def _read_faults(self, version: float) -> None:
        assert self._shm is not None
        c = self._c
        for _ in range(3):
            done = int(c[_C_FA_DONE])
            raw = bytes(self._shm.buf[self._layout.off_fa:self._layout.off_fa + _FAULT_BYTES])
            if int(c[_C_FA_BEGUN]) == done:
                size = int.from_bytes(raw[:4], "little")
                try:
                    data = json.loads(raw[4:4 + size]) if size else {}
                except ValueError:
                    continue
                self._faults = {k: (int(v[0]), str(v[1])) for k, v in data.items()}
                self._faults_version = float(done)
                return

    # ------------------------------------------------------------------ lifecycle requests (loop side)
    def request(self, op: str) -> int:
        """Ask for ``"enable"``, ``"disable"`` or ``"reset"`` (fault reset); returns a ticket for :meth:`result`."""
        if op not in OPS:
            raise ValueError(f"bus {self.name!r}: unknown operation {op!r}; known: {', '.join(OPS)}")
        ticket = next(self._tickets)
        if self._ctrl is None or self._proc is None or not self._proc.is_alive():
            self._results[ticket] = (False, f"bus {self.name!r}: bus process is not running")
            return ticket
        try:
            self._ctrl.send((op, ticket))
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
                msg = conn.recv()
                if msg[0] == "result":
                    self._results[msg[1]] = (bool(msg[2]), str(msg[3]))

    def __enter__(self) -> BusLink:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _recreate(info: tuple[str, str, str, dict[str, Any]], bus: str) -> Exception:
    """The driver's typed error, rebuilt from (module, class, message, attributes); others as BusInitError."""
    module, cls_name, message, attrs = info
    cls = getattr(bus_errors, cls_name, None) if module == bus_errors.__name__ else None
    if isinstance(cls, type) and issubclass(cls, bus_errors.BusError):
        exc = cls.__new__(cls)
        Exception.__init__(exc, message)
        exc.__dict__.update(attrs)
        return exc
    return BusInitError(f"bus {bus!r}: {cls_name}: {message}")


def _describe(exc: BaseException) -> tuple[str, str, str, dict[str, Any]]:
    attrs = {k: v for k, v in vars(exc).items() if isinstance(v, (str, int, float))}
    return type(exc).__module__, type(exc).__name__, str(exc), attrs


# ---------------------------------------------------------------------- the bus process
class _BusServer:
    """Runs in the bus process: transactions on wake-up or at the idle rate, lifecycle requests in between."""

    def __init__(self, cfg: BusProcessConfig, shm: SharedMemory, ctrl: Connection, wake: Connection) -> None:
        from drivers.registry import create_bus

        self.cfg = cfg
        self.shm = shm
        self.ctrl = ctrl
        self.wake_fd = wake.fileno()
        os.set_blocking(self.wake_fd, False)
        motors = [MotorConfig(**m) for m in cfg.motors]
        self.names = [m.name for m in motors]
        self.layout = _Layout(len(motors))
        self.c, self.fb, self.tg, self.fa = self.layout.views(shm.buf)
        self.bus = create_bus(cfg.driver, cfg.name, cfg.options, motors)
        self.connected = False
        self.seq = 0
        self.written = np.full(len(motors), np.nan)
        self.write_stamp = 0.0
        self.io_us = 0.0
        self.written_k = 0
        self.enabled_k = 1 << 62  # nothing is written before an enable
        self.faults_seen: dict[str, tuple[int, str]] = {}
        self.faults_version = 0
        self.last_error = ""
        self.link = "closed"
        self.attempts = 0
        self.retry_at = math.inf
        self.reconnect_error = ""
        self.parent = os.getppid()

    # -------------------------------------------------------------- publication
    def publish(self, states: Mapping[str, Any] | None) -> None:
        c = self.c
        k = int(c[_C_FB_DONE]) + 1
        faults = self.bus.faults()
        if faults != self.faults_seen:
            self.publish_faults(faults)
        c[_C_FB_BEGUN] = k
        buf = self.fb[k & 1]
        n = len(self.names)
        h = _N_HEADER
        if states is not None:
            self.seq += 1
            stamps = [states[m].timestamp for m in self.names]
            buf[h:h + n] = [states[m].position for m in self.names]
            buf[h + n:h + 2 * n] = [states[m].velocity for m in self.names]
            buf[_H_STAMP] = min(stamps)
        else:
            prev = self.fb[(k - 1) & 1]
            buf[:] = prev
        buf[_H_SEQ] = self.seq
        buf[h + 2 * n:h + 3 * n] = self.written
        buf[_H_WSTAMP] = self.write_stamp
        buf[_H_IO_US] = self.io_us
        buf[_H_STATE] = _STATE_CODE[self.bus.state]
        buf[_H_CONNECTED] = 1.0 if self.connected and self.bus.state is not LifecycleState.UNCONFIGURED else 0.0
        buf[_H_FAULTS] = self.faults_version
        buf[_H_LINK] = _LINK_CODE[self.link]
        buf[_H_ATTEMPTS] = self.attempts
        buf[_H_RETRY_AT] = self.retry_at
        c[_C_FB_DONE] = k

    def publish_faults(self, faults: dict[str, tuple[int, str]]) -> None:
        data = {k: [int(v[0]), str(v[1])[:300]] for k, v in faults.items()}
        raw = json.dumps(data).encode()
        while len(raw) > _FAULT_BYTES - 4 and data:
            data.popitem()
            raw = json.dumps(data).encode()
        v = self.faults_version + 1
        self.c[_C_FA_BEGUN] = v
        self.fa[:4] = np.frombuffer(len(raw).to_bytes(4, "little"), np.uint8)
        self.fa[4:4 + len(raw)] = np.frombuffer(raw, np.uint8)
        self.c[_C_FA_DONE] = v
        self.faults_version = v
        self.faults_seen = dict(faults)

    def latest_targets(self) -> tuple[int, np.ndarray | None]:
        """(post counter, [stamp, targets...]) of the latest consistent post, or (last written, None)."""
        c = self.c
        for _ in range(5):
            k = int(c[_C_TG_DONE])
            if k == 0:
                return 0, None
            snap = self.tg[k & 1].copy()
            if int(c[_C_TG_BEGUN]) < k + 2:
                return k, snap
        return self.written_k, None

    # -------------------------------------------------------------- transactions
    def transaction(self) -> None:
        t0 = time.monotonic()
        states = None
        if not self.connected:  # nothing to talk to until a reconnect attempt succeeds
            self.publish(None)
            return
        try:
            k = int(self.c[_C_TG_DONE])
            if k != self.written_k and k > self.enabled_k and self.bus.state is LifecycleState.ACTIVE:
                k, snap = self.latest_targets()
                if snap is not None:
                    self.written_k = k
                    targets = snap[1:]
                    # rate check against the loop's own timing: a delay in this process must not fault the bus
                    self.bus.write(dict(zip(self.names, targets.tolist(), strict=True)), stamp=float(snap[0]))
                    self.written = targets
                    self.write_stamp = time.monotonic()
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

    def lose(self, why: str) -> None:
        """The transport is gone: stop all I/O and plan the first reconnect attempt."""
        self.connected = False
        self.link = "lost"
        self.attempts = 0
        self.retry_at = time.monotonic() + self.cfg.reconnect_base_s
        log.error("bus %s: connection lost (%s); reopening in the background", self.bus.name, why)

    def reconnect(self) -> bool:
        """One attempt to open the bus again (closing what is left of it first); on failure the next attempt is
        planned after an exponentially growing wait. True once the bus is open (inactive, torque off)."""
        self.attempts += 1
        self.link = "reconnecting"
        self.retry_at = math.inf
        self.publish(None)
        with contextlib.suppress(Exception):
            self.bus.close()
        try:
            self.bus.open()
        except Exception as exc:
            delay = min(self.cfg.reconnect_max_s, self.cfg.reconnect_base_s * 2.0 ** self.attempts)
            self.retry_at = time.monotonic() + delay
            self.link = "lost"
            self.reconnect_error = f"{type(exc).__name__}: {exc}"
            log.warning("bus %s: reconnect attempt %d failed (%s); next in %.2g s", self.bus.name, self.attempts,
                        self.reconnect_error, delay)
            with contextlib.suppress(Exception):
                self.bus.close()
            self.publish(None)
            return False
        self.connected = True
        self.link = "connected"
        self.retry_at = math.inf
        self.last_error = self.reconnect_error = ""
        self.written_k = self.enabled_k = 1 << 62  # nothing is written before the next enable
        log.warning("bus %s: reopened after %d reconnect attempt(s); send reset, then enable", self.bus.name,
                    self.attempts)
        self.publish(None)
        return True

    def open(self) -> None:
        attempts = self.cfg.open_attempts
        for attempt in range(1, attempts + 1):
            try:
                self.bus.open()
                self.connected = True
                self.link = "connected"
                return
            except bus_errors.ConfigError:
                raise
            except Exception as exc:
                if attempt == attempts:
                    raise
                log.warning("bus %s: open attempt %d failed (%s); retrying", self.bus.name, attempt, exc)
                with contextlib.suppress(Exception):
                    self.bus.close()

    def lifecycle(self, op: str) -> None:
        bus = self.bus
        if op == "enable":
            if bus.state is not LifecycleState.ACTIVE:
                bus.enable()
            self.enabled_k = int(self.c[_C_TG_DONE])
            self.written_k = self.enabled_k
        elif op == "disable":
            if bus.state is LifecycleState.ACTIVE:
                bus.disable()
        elif op == "reset":
            if not self.connected or bus.state is LifecycleState.UNCONFIGURED:
                if not self.reconnect():
                    raise BusConnectionLost(
                        f"bus {bus.name!r} is still unreachable ({self.reconnect_error}); reconnect attempt "
                        f"{self.attempts}, next in {max(0.0, self.retry_at - time.monotonic()):.2g} s")
            elif bus.state is LifecycleState.FAULT:
                bus.reset_fault()
                self.last_error = ""
        else:
            raise ValueError(f"unknown operation {op!r}")

    def handle_requests(self) -> bool:
        """Carry out queued lifecycle requests; False when asked to stop."""
        while self.ctrl.poll(0):
            try:
                op, ticket = self.ctrl.recv()
            except (EOFError, OSError):
                return False
            if op == "stop":
                return False
            try:
                self.lifecycle(op)
                reply = ("result", ticket, True, "")
            except Exception as exc:
                if not isinstance(exc, bus_errors.LifecycleError) and self.connected:
                    self.fail(exc)
                reply = ("result", ticket, False, f"{type(exc).__name__}: {exc}")
            self.publish(None)
            try:
                self.ctrl.send(reply)
            except (OSError, ValueError):
                return False
        return True

    def serve(self) -> None:
        period = 1.0 / self.cfg.idle_hz
        poller = select.poll()
        poller.register(self.wake_fd, select.POLLIN)
        poller.register(self.ctrl.fileno(), select.POLLIN)
        next_idle = time.monotonic()
        while True:
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
            fresh = self.bus.state is LifecycleState.ACTIVE and int(self.c[_C_TG_DONE]) != self.written_k
            if (woken and fresh) or now >= next_idle:
                self.transaction()
                next_idle = max(next_idle + period, time.monotonic()) if now >= next_idle else next_idle


def _connection_lost(exc: BaseException) -> bool:
    """Whether a driver error means the transport is gone (rather than a device fault or a missed answer)."""
    return isinstance(exc, (OSError, BusConnectionLost)) or type(exc).__module__.startswith(("serial", "can."))


def _bus_main(cfg: BusProcessConfig, shm_name: str, ctrl: Connection, wake: Connection) -> None:
    """Entry point of the bus process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops this process; Ctrl-C reaches the parent

    def _terminate(*_: object) -> None:
        raise SystemExit(0)  # SIGTERM (e.g. multiprocessing's exit handler): leave through the torque-off below

    signal.signal(signal.SIGTERM, _terminate)
    logging.basicConfig(level=cfg.log_level, format=f"%(asctime)s bus {cfg.name} %(levelname)s %(message)s")
    if cfg.nice:
        with contextlib.suppress(OSError):
            os.nice(cfg.nice)
    if cfg.realtime_priority is not None:
        from runtime.loop import try_realtime

        ok, message = try_realtime(cfg.realtime_priority)
        (log.info if ok else log.warning)("bus %s: %s", cfg.name, message)
    shm = SharedMemory(name=shm_name)
    server: _BusServer | None = None
    try:
        try:
            server = _BusServer(cfg, shm, ctrl, wake)
            server.open()
        except Exception as exc:
            with contextlib.suppress(OSError, ValueError):
                ctrl.send(("open", False, _describe(exc)))
            return
        server.publish(None)
        server.transaction()
        ctrl.send(("open", True, None))
        server.serve()
    finally:
        if server is not None:
            with contextlib.suppress(Exception):
                server.bus.close()
            server.connected = False
            with contextlib.suppress(Exception):
                server.publish(None)
            server.c = server.fb = server.tg = server.fa = None  # type: ignore[assignment]
        with contextlib.suppress(BufferError):
            shm.close()
