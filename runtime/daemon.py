"""The daemon: assembles the control core, its loop runner, the buses and the API server process, and tears them down.

Processes and threads (``docs/architecture.md`` draws them):

- this process: the loop runner's thread (the only realtime thread) stepping :mod:`runtime.core`, and the caller's
  thread, which only starts and stops things and forwards signals;
- the API server process (:mod:`runtime.server`): ZeroMQ command and telemetry sockets, decoding and validation,
  clip compilation, telemetry formatting, recording files; it hands the loop commands over the command pipe and
  hears back over a PAIR socket (:mod:`runtime.ipc` moves the bytes, :mod:`runtime.loop_messages` types them);
- the buses: each driver runs off the loop's critical path (the loop posts targets and takes the latest feedback);
- emulated hardware (``simulated = true``): the emulators, started by :mod:`runtime.hardware`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import zmq

from models.errors import StartError
from models.headspec import HeadSpec
from runtime import ipc
from runtime import loop_messages as L
from runtime import server as server_mod
from runtime.bus import BusProxy
from runtime.compiled import prepare_kernels
from runtime.config import DaemonConfig, daemon_config
from runtime.core.channels import ChannelMap
from runtime.core.commands import Command
from runtime.core.cycle import CycleInputs
from runtime.core.params import CoreParams
from runtime.core.solvers import as_array_solvers, channel_sets
from runtime.core.state import CoreState
from runtime.hardware import Hardware
from runtime.predictor_check import PredictorCheck
from runtime.runner import Runner
from runtime.solve import TargetSolver
from runtime.strain_check import FullStrainCheck

if TYPE_CHECKING:
    from models.strain_guard import StrainGuard

log = logging.getLogger(__name__)

SERVER_START_TIMEOUT_S = 60.0
#: Niceness added to the API server process: requests and telemetry stay timely on a busy host (the control loop
#: itself runs SCHED_FIFO and preempts it). Needs CAP_SYS_NICE; without it the server keeps the daemon's niceness.
SERVER_NICE = -10
#: Niceness added to the bus processes: a device fault or a lost heartbeat reaches the loop within a few ms on a busy
#: host, as the drives' own timing assumes. Needs CAP_SYS_NICE; without it they keep the daemon's niceness.
BUS_NICE = -10


class DaemonStartError(StartError, RuntimeError):
    """The daemon could not start (a bus, the API server or the loop); the message says which and why."""


class Daemon:
    """One head's daemon. ``start()`` opens the buses and serves; ``stop()`` disables torque and closes everything."""

    def __init__(self, head: HeadSpec, overrides: Mapping[str, object] | None = None,
                 hardware: Hardware | None = None, target_solvers: Iterable[TargetSolver] | None = None,
                 record_inputs: bool = False, strain_guard: bool = True) -> None:
        self.head = head
        self.overrides = dict(overrides or {})
        self.cfg: DaemonConfig = daemon_config(head, self.overrides)
        predictor = head.path("predictor")
        check = None if predictor is None or not predictor.is_file() else PredictorCheck(predictor, _child_env())
        try:
            self._build(head, hardware, target_solvers, record_inputs, strain_guard)
            if check is not None:
                check.result()  # onnxruntime itself accepts the predictor (checked while the rest was built)
        finally:
            if check is not None:
                check.cancel()

    def _build(self, head: HeadSpec, hardware: Hardware | None, target_solvers: Iterable[TargetSolver] | None,
               record_inputs: bool, strain_guard: bool) -> None:
        """Everything the daemon is made of before it starts (solvers, guard, inputs, asset checks)."""
        self.names = head.actuator_names
        self.period = 1.0 / self.cfg.runtime.rate_hz
        if target_solvers is None:
            from runtime.skin import default_target_solvers

            target_solvers = default_target_solvers(head)
        self.target_solvers: list[TargetSolver] = list(target_solvers)
        self.channels = ChannelMap.build(head, channel_sets(self.target_solvers))
        self.guard = _strain_guard(head, self.target_solvers) if strain_guard else None
        prepare_kernels()  # the cycle's own kernels: loaded now, not in the first cycle that calls one
        from runtime.inputs.config import inputs_config

        self.inputs = inputs_config(head, self.channels)  # [inputs]: checked here, served by the API server
        _check_server_assets(head)
        self.hw = hardware
        self._own_hw = hardware is None
        self.buses: list[BusProxy] = []
        self.params: CoreParams | None = None
        self.state: CoreState | None = None
        self.runner: Runner | None = None
        self.input_log: list[CycleInputs] | None = [] if record_inputs else None
        self.command_endpoint = ""
        self.telemetry_endpoint = ""
        self._thread: threading.Thread | None = None
        self._server: subprocess.Popen[bytes] | None = None
        self._ctx: zmq.Context | None = None
        self._sock: zmq.Socket | None = None
        self._estop: ipc.EStopFlag | None = None
        self._tmp: str | None = None
        self._commands: ipc.PipeReader[Command] | None = None

    @property
    def realtime_status(self) -> str:
        return self.runner.realtime_status if self.runner is not None else "not started"

    @property
    def lifecycle(self) -> str:
        return self.state.lifecycle.value if self.state is not None else "unconfigured"

    # ------------------------------------------------------------------ start / stop
    def start(self) -> None:
        """Open the buses, start the API server process and the control loop; raises :class:`DaemonStartError`."""
        try:
            self._start_buses()
            self._start_pipes()
            self._start_server()
            self._start_loop()
        except BaseException:
            self.stop()
            raise
        if self.cfg.runtime.auto_enable:
            from models.client import Client

            with Client(self.command_endpoint, timeout=30.0) as c:
                c.call("enable")

    def _start_buses(self) -> None:
        """Every bus in a process of its own (emulators first, as processes too, for simulated buses)."""
        if self.hw is None:
            rt = self.cfg.runtime
            self.hw = Hardware.from_head(self.head, bus_nice=BUS_NICE,
                                     realtime_priority=(rt.bus_priority or None) if rt.realtime else None,
                                     write_priority=rt.bus_write_priority if rt.realtime else 0)
        self.hw.start()
        self.buses = list(self.hw.proxies.values())

    def _start_pipes(self) -> None:
        """The PAIR socket the server hears the loop on, the command pipe the loop reads, the shared e-stop flag."""
        self._tmp = tempfile.mkdtemp(prefix="likeness-")
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.PAIR)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.SNDHWM, 10000)
        self._sock.bind(f"ipc://{self._tmp}/loop")
        ipc.make_pipe(f"{self._tmp}/commands")
        self._commands = ipc.PipeReader[Command](f"{self._tmp}/commands")  # opened before the server opens its end
        self._estop = ipc.EStopFlag()

    def _start_server(self) -> None:
        assert self._sock is not None and self._estop is not None and self._tmp is not None
        spec = server_mod.ServerSpec(str(self.head.source), self.overrides, self.channels, f"ipc://{self._tmp}/loop",
                                     f"{self._tmp}/commands",
                                     self._estop.name, self.cfg.safety.safe_speed,
                                     logging.getLogger().getEffectiveLevel(),
                                     strain_check=None if self.guard is None else FullStrainCheck.of(self.guard))
        # A fresh interpreter (not multiprocessing's spawn, which re-imports the caller's main script): the spec
        # travels pickled on its standard input.
        self._server = subprocess.Popen([sys.executable, "-m", "runtime.server"], stdin=subprocess.PIPE,
                                        cwd=os.getcwd(), env=_child_env())
        _renice(self._server.pid, SERVER_NICE)
        assert self._server.stdin is not None
        self._server.stdin.write(pickle.dumps(spec))
        self._server.stdin.close()
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        while True:
            if self._sock.poll(100):
                ready = L.recv_ready(self._sock)
                if ready is not None:
                    self.command_endpoint, self.telemetry_endpoint = ready.command_endpoint, ready.telemetry_endpoint
                    break
            if self._server.poll() is not None:
                raise DaemonStartError(f"the API server process exited with code {self._server.returncode} "
                                  "(endpoint in use? see the log)")
            if time.monotonic() > deadline:
                raise DaemonStartError("the API server process did not start")
        log.info("commands on %s, telemetry on %s", self.command_endpoint, self.telemetry_endpoint)

    def _start_loop(self) -> None:
        assert self._sock is not None and self._estop is not None and self._commands is not None
        self.params = CoreParams.build(self.head, self.cfg, self.channels,
                                         [(bus.name, bus.actuators) for bus in self.buses], guard=self.guard,
                                         chase=None if self.inputs.timecode is None else self.inputs.timecode.chase)
        solvers = as_array_solvers(self.target_solvers, self.channels.target_blocks, self.channels.names,
                                   self.names)
        self.state = CoreState.initial(self.head, self.params, solvers)
        self.runner = Runner(self.params, self.state, self.buses, self._sock, self._commands, self._estop,
                             input_log=self.input_log)
        self._thread = threading.Thread(target=self.runner.run, name="likeness-control", daemon=True)
        self._thread.start()
        if not self.runner.ready.wait(10.0):
            raise DaemonStartError("control loop did not start")

    def stop(self) -> None:
        """Stop the loop and the server, torque off, close buses and emulators; safe to call twice."""
        if self.runner is not None:
            self.runner.stop()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._sock is not None:
            with contextlib.suppress(zmq.ZMQError):
                L.send_to_server(self._sock, L.StopServer(), zmq.NOBLOCK)
        if self._server is not None:
            try:
                self._server.wait(timeout=3.0)
            except subprocess.TimeoutExpired:
                self._server.terminate()
                try:
                    self._server.wait(timeout=2.0)
                except subprocess.TimeoutExpired:
                    self._server.kill()
                    self._server.wait()
            self._server = None
        if self.hw is not None and self._own_hw:
            self.hw.stop()  # torque off, close every bus, stop the emulators
        self.buses = []
        if self._sock is not None:
            self._sock.close(0)
            self._sock = None
        if self._commands is not None:
            self._commands.close()
            self._commands = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None
        if self._estop is not None:
            self._estop.close()
            self._estop = None
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ conveniences for callers in this process
    def estop(self, reason: str = "signal") -> None:
        """Latch the e-stop from this process (a signal handler): taken by the next cycle."""
        if self.runner is not None:
            self.runner.trip_estop(reason)

    def call(self, op: str, **fields: object) -> dict[str, object]:
        """One request through the public protocol (for tools and tests in the daemon's process)."""
        from models.client import Client

        with Client(self.command_endpoint, timeout=30.0) as c:
            return c.call(op, **fields)

    def enable(self) -> None:
        self.call("enable")




def _child_env() -> dict[str, str]:
    """The environment for child processes: this one, with the project root importable."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in paths:
        env["PYTHONPATH"] = os.pathsep.join([root, *paths])
    return env


def _renice(pid: int, delta: int) -> None:
    """Add ``delta`` to a child's niceness (best effort)."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0) + delta)
    except OSError as exc:
        log.debug("process %d keeps its niceness (%s)", pid, exc)


def _strain_guard(head: HeadSpec, solvers: list[TargetSolver]) -> StrainGuard | None:
    """The skin-strain guard of the safety stage: the skin solver's own (one build), else the head's predictor's,
    else None (a head without a skin predictor has no strain guard)."""
    for solver in solvers:
        guard = getattr(solver, "strain_guard", None)
        if guard is not None:
            return guard
    from models.strain_guard import StrainGuard

    return StrainGuard.for_head(head)


def _check_server_assets(head: HeadSpec) -> None:
    """Read the files only the API server uses (the link map, for telemetry's attachment-link poses) once here, so a
    corrupt one stops the daemon at start with a ``SpecError`` naming the file, before any process starts."""
    from models.linkmap import LinkMap

    path = head.path("linkmap")
    if path is not None and path.exists():
        LinkMap.for_head(head)
