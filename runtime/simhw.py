"""Emulated buses for heads whose config says ``simulated = true``, each emulator in a child process.

:func:`start` launches ``likeness sim canopen`` (a socketcand server on a free loopback port) or ``likeness sim
dynamixel`` (a pseudo-terminal) with ``sys.executable -m likeness.cli``, waits for its ``ready:`` line, and returns a
:class:`SimProcess`: the bus options the real driver must use to reach it, ground truth in encoder counts by device
id and fault injection, both over the emulator's control endpoint (:func:`models.emulator_control.request`:
msgpack maps over ZeroMQ; the runtime never imports the emulators). The emulator
exits with this process (``--watch-parent``); a supervising thread logs its output and notices when it dies.
:meth:`SimProcess.restart` brings a dead emulator back on the same socketcand port or pseudo-terminal path, as a
device server or a replugged adapter comes back, so the daemon's bus can reconnect to it.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import queue
import re
import secrets
import socket
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence

from drivers.base import MotorConfig
from drivers.errors import BusInitError, ConfigError
from models.emulator_control import ControlReply, request

log = logging.getLogger(__name__)

#: Seconds to wait for an emulator's ``ready:`` line (a cold Python start with canopen imports takes ~1 s).
READY_TIMEOUT_S = 20.0
#: Niceness added to emulator processes by default. An emulator stands in for hardware that never waits for a CPU:
#: on a loaded 2-core machine a driver's fixed reply window (Dynamixel SDK: ~34 ms at 4 Mbaud) is missed when the
#: emulator queues behind ordinary processes. A SCHED_FIFO control thread still preempts it. Needs CAP_SYS_NICE;
#: without it the emulator keeps the parent's niceness.
EMULATOR_NICE = -10

#: An emulator's reply on its control endpoint: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``.

#: Emulators still running, stopped at interpreter exit if their owner did not close them.
_RUNNING: weakref.WeakSet[SimProcess] = weakref.WeakSet()


@atexit.register
def _close_all() -> None:
    for sim in list(_RUNNING):
        sim.close()


class SimProcess:
    """One emulator child process: driver options to reach it, ground truth and fault injection.

    ``positions_counts()`` and the injection calls are control-channel round trips (about a millisecond): call them
    from supervision or test code, never from a control cycle.
    """

    def __init__(
        self,
        driver: str,
        bus_name: str,
        proc: subprocess.Popen[str],
        control: str,
        cleanup: Callable[[], None] | None = None,
        command: Sequence[str] = (),
        nice: int = 0,
    ) -> None:
        self.driver = driver
        self.bus_name = bus_name
        self.options: dict[str, object] = {}
        self.control = control
        self._proc = proc
        self._command = list(command)
        self._nice = nice
        self._cleanup = cleanup
        self._closing = False
        self._early: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._watch = threading.Thread(target=self._supervise, name=f"sim-{bus_name}-watch", daemon=True)
        self._watch.start()
        _RUNNING.add(self)

    def wait_ready(self, timeout_s: float) -> str:
        """The emulator's ``ready:`` line; BusInitError with its output if it exits or stays silent."""
        seen: list[str] = []
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                line = self._early.get(timeout=max(left, 0.0)) if left > 0 else None
            except queue.Empty:
                line = None
            if line is None:
                why = f"exited with code {self._proc.poll()}" if self._proc.poll() is not None \
                    else f"did not report ready in {timeout_s} s"
                raise BusInitError(f"bus {self.bus_name}: emulator {why}; output: {' | '.join(seen[-8:]) or 'none'}")
            if line.startswith("ready:"):
                return line
            seen.append(line)

    # ------------------------------------------------------------------ process
    @property
    def pid(self) -> int:
        """Process id of the emulator (of the latest one after a restart)."""
        return self._proc.pid

    @property
    def alive(self) -> bool:
        """Whether the emulator process is still running."""
        return self._proc.poll() is None

    def _supervise(self) -> None:
        """Forward the emulator's output to the log until it exits, then say so (an unexpected exit is an error)."""
        out = self._proc.stdout
        ready = False
        if out is not None:
            with contextlib.suppress(ValueError, OSError):
                for raw in out:
                    line = raw.rstrip()
                    if not ready:
                        self._early.put(line)
                        ready = line.startswith("ready:")
                    # an emulator's own warnings (it cannot keep its rate, a failed send) reach the daemon's log
                    level = logging.WARNING if (" WARNING " in line or " ERROR " in line) else logging.INFO
                    log.log(level, "emulator %s: %s", self.bus_name, line)
        self._early.put(None)
        code = self._proc.wait()
        if not self._closing:
            log.error("emulator of bus %s (pid %d) exited unexpectedly with code %s", self.bus_name, self.pid, code)

    def kill(self) -> None:
        """Kill the emulator at once (tests use this to simulate a crashed device server)."""
        with contextlib.suppress(ProcessLookupError):
            self._proc.kill()
        self._proc.wait()

    def restart(self, timeout_s: float = READY_TIMEOUT_S) -> str:
        """Start the emulator again after it died or was killed, reachable where it was before (same socketcand port,
        same pseudo-terminal path); its devices boot afresh at their initial positions. Returns the ready line;
        RuntimeError while it still runs, BusInitError if it does not come up."""
        if self.alive:
            raise RuntimeError(f"emulator of bus {self.bus_name} is still running (pid {self.pid})")
        if self._closing or not self._command:
            raise RuntimeError(f"emulator of bus {self.bus_name} was closed; start a new one")
        self._watch.join(timeout=1.0)
        self._proc = _spawn(self._command, self.bus_name, self._nice)
        self._early = queue.SimpleQueue()
        self._watch = threading.Thread(target=self._supervise, name=f"sim-{self.bus_name}-watch", daemon=True)
        self._watch.start()
        line = self.wait_ready(timeout_s)
        log.warning("emulator of bus %s restarted (pid %d): %s", self.bus_name, self.pid, line)
        return line

    def close(self, timeout_s: float = 3.0) -> None:
        """Terminate the emulator (kill after ``timeout_s``) and remove what it left; idempotent, never raises."""
        self._closing = True
        _RUNNING.discard(self)
        if self._proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self._proc.terminate()
            try:
                self._proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("emulator of bus %s did not stop in %.1f s; killing it", self.bus_name, timeout_s)
                self.kill()
        self._watch.join(timeout=1.0)
        if self._proc.stdout is not None:
            with contextlib.suppress(OSError):
                self._proc.stdout.close()
        if self._cleanup is not None:
            cleanup, self._cleanup = self._cleanup, None
            with contextlib.suppress(Exception):
                cleanup()

    # ------------------------------------------------------------------ control channel
    def _request(self, message: Mapping[str, object], timeout_s: float = 2.0) -> ControlReply:
        reply = request(self.control, message, timeout_s=timeout_s)
        if not reply.get("ok"):
            raise RuntimeError(f"emulator of bus {self.bus_name}: {reply.get('error', 'request failed')}")
        return reply

    def positions_counts(self) -> dict[int, float]:
        """Ground-truth positions in encoder counts by device id, from the emulator (not through the driver)."""
        positions = self._request({"op": "positions"}).get("positions")
        if not isinstance(positions, dict):
            raise RuntimeError(f"emulator of bus {self.bus_name}: no positions in its reply")
        return {int(k): float(v) for k, v in positions.items()}

    def inject(self, fault: str, device: int | None = None, **params: object) -> ControlReply:
        """Start a fault by the emulator's name for it (canopen: ``stop_heartbeat``, ``drive_fault``, ``jam``...;
        dynamixel: ``overheat``, ``disconnect``, ``drop``...) on ``device`` (an id) with its parameters."""
        if device is not None:
            params["device"] = int(device)
        return self._request({"op": "inject", "fault": fault, **params})

    def clear(self, fault: str | None = None, device: int | None = None) -> ControlReply:
        """End injected faults: all of them, or (dynamixel) one kind or one device's."""
        if self.driver == "canopen402":
            if fault is not None or device is not None:
                return self.inject(fault or "resume_heartbeat", device=device)
            return self.inject("clear")
        msg: dict[str, object] = {"op": "clear"}
        if fault is not None:
            msg["fault"] = fault
        if device is not None:
            msg["device"] = device
        return self._request(msg)


def start(
    driver: str,
    bus_name: str,
    options: Mapping[str, object],
    motors: Sequence[MotorConfig],
    initial: Mapping[str, float] | None = None,
    *,
    ready_timeout_s: float = READY_TIMEOUT_S,
    nice: int = EMULATOR_NICE,
) -> SimProcess:
    """Start the emulator of ``driver`` serving ``motors`` in a child process, each motor at ``initial[name]`` (SI,
    default 0); ``SimProcess.options`` are ``options`` rewritten so the real driver reaches it.

    ``nice`` is added to the child's niceness. ConfigError for a driver without an emulator; BusInitError when the
    emulator does not come up (its output is in the message).
    """
    if driver not in _ARGS:
        raise ConfigError(f"buses.{bus_name}.simulated", f"no emulator for driver {driver!r}")
    counts = {m.device_id: m.to_counts((initial or {}).get(m.name, 0.0)) for m in motors}
    ids = ",".join(str(m.device_id) for m in motors)
    start_at = ",".join(f"{k}={v}" for k, v in counts.items())
    control = f"tcp://127.0.0.1:{_free_port()}"
    # a fresh path in the temp directory; the Dynamixel emulator makes it a symlink to its pty and removes it on exit
    pty_path = os.path.join(tempfile.gettempdir(), f"likeness-{bus_name}-{os.getpid()}-{secrets.token_hex(6)}")
    args = _ARGS[driver](ids, start_at, control, pty_path, dict(options))
    cmd = [sys.executable, "-m", "likeness.cli", "sim", *args, "--watch-parent"]
    proc = _spawn(cmd, bus_name, nice)
    sim = SimProcess(driver, bus_name, proc, control, lambda: _remove_symlink(pty_path), cmd, nice)
    try:
        line = sim.wait_ready(ready_timeout_s)
        sim.options = _OPTIONS[driver](line, dict(options), pty_path)
        if "--port" in cmd:  # a restart listens where the driver already connects
            sim._command[cmd.index("--port") + 1] = str(sim.options["port"])
    except BaseException:
        sim.close()
        raise
    log.info("emulator of bus %s running (pid %d): %s", bus_name, proc.pid, line)
    return sim


def _spawn(cmd: Sequence[str], bus_name: str, nice: int) -> subprocess.Popen[str]:
    """Start one emulator process (output piped, unbuffered) and add ``nice`` to its niceness (best effort)."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    try:
        proc = subprocess.Popen(
            list(cmd), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, env=env,
        )
    except OSError as exc:
        raise BusInitError(f"bus {bus_name}: cannot start emulator ({exc})") from exc
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, proc.pid, os.getpriority(os.PRIO_PROCESS, 0) + nice)
        except OSError as exc:
            log.debug("emulator of bus %s keeps its niceness (%s)", bus_name, exc)
    return proc


def _remove_symlink(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        if os.path.islink(path):
            os.unlink(path)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _canopen_args(ids: str, start_at: str, control: str, pty_path: str, options: dict[str, object]) -> list[str]:
    channel = str(options.get("channel") or "can0")
    if options.get("interface") not in (None, "virtual", "socketcand"):
        log.info("simulated bus: interface %r replaced by socketcand to reach the emulator", options["interface"])
    return ["canopen", "--nodes", ids, "--initial-positions", start_at, "--port", "0", "--channel", channel,
            "--control", control]


def _canopen_options(line: str, options: dict[str, object], pty_path: str) -> dict[str, object]:
    match = re.search(r"on socketcand (\S+):(\d+) channel (\S+?)(?:,|$)", line)
    if match is None:
        raise BusInitError(f"cannot parse the canopen emulator's ready line: {line!r}")
    options.update(interface="socketcand", host=match.group(1), port=int(match.group(2)), channel=match.group(3))
    return options


def _dynamixel_args(ids: str, start_at: str, control: str, pty_path: str, options: dict[str, object]) -> list[str]:
    model = str(options.get("model", "XM430-W350"))
    return ["dynamixel", "--ids", ids, "--model", model, "--initial-positions", start_at,
            "--link", pty_path, "--control", control]


def _dynamixel_options(line: str, options: dict[str, object], pty_path: str) -> dict[str, object]:
    options["port"] = pty_path
    return options


_ARGS: dict[str, Callable[[str, str, str, str, dict[str, object]], list[str]]] = {
    "canopen402": _canopen_args,
    "dynamixel": _dynamixel_args,
}
_OPTIONS: dict[str, Callable[[str, dict[str, object], str], dict[str, object]]] = {
    "canopen402": _canopen_options,
    "dynamixel": _dynamixel_options,
}

