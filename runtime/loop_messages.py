"""What the loop process and the API server process tell each other: one typed message union each way.

Server → loop, over the command pipe (:class:`runtime.ipc.PipeWriter` → :class:`runtime.ipc.PipeReader`):
:data:`ToLoop`, the core's ready-made commands (:mod:`runtime.core.commands`), nothing else.

Loop → server, over the ZeroMQ PAIR socket (:func:`send_to_server` → :func:`recv_from_loop`): :data:`FromLoop`,
frozen dataclasses the server matches on: a command's :class:`Reply`, an :class:`Event`, a telemetry
:class:`StateSnapshot`, the loop's :class:`LoopStatistics`, :class:`RecordedRows` for the recording file, the loop
thread's :class:`RealtimeStatus`, and the daemon's :class:`StopServer`. Once, at start-up, the server answers on the
same socket with :class:`ServerReady`. The maps inside (reply bodies, events, snapshots) are built by the core;
their keys are the protocol's (``docs/protocol.md``) and the server formats them for clients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import zmq

from models.errors import InternalError
from runtime import ipc
from runtime.core.commands import Command
from runtime.core.events import Body

#: Server → loop: every message on the command pipe is one of the core's commands.
ToLoop = Command



@dataclass(frozen=True, slots=True)
class Reply:
    """The core's answer to the command carrying ``token``: the reply's fields, or ``{"error": {code, message}}``."""

    token: int
    body: Body


@dataclass(frozen=True, slots=True)
class Event:
    """An event to publish on the telemetry socket (``{"event": kind, "t": ..., ...}``)."""

    body: Body


@dataclass(frozen=True, slots=True)
class StateSnapshot:
    """The core's state for telemetry (positions SI, lifecycle, buses...), formatted by the server off its thread."""

    body: Body


@dataclass(frozen=True, slots=True)
class PhaseLockReport:
    """The stream phase lock's state: whether it holds, and its last phase error (µs; None before any frame)."""

    locked: bool
    error_us: float | None


@dataclass(frozen=True, slots=True)
class LoopStatistics:
    """The loop's timing over its recent window (seconds): the server summarises it for ``status`` and telemetry."""

    period: float
    cycles: int
    missed: int
    skipped: int
    lateness: np.ndarray
    work: np.ndarray
    periods: np.ndarray
    phase_lock: PhaseLockReport | None = None
    early: int = 0  # cycles run ahead of their deadline on an input's arrival (``[runtime] wake_on_input``)

    def summary(self) -> Body:
        """Rate, counts and percentiles (µs) as ``status`` reports them under ``loop``."""
        out: Body = {"rate_hz": 1.0 / self.period, "cycles": self.cycles, "missed": self.missed,
                        "skipped": self.skipped, "early": self.early}
        if self.phase_lock is not None:
            out["stream_phase_lock"] = {"locked": self.phase_lock.locked, "error_us": self.phase_lock.error_us}
        if len(self.lateness):
            lat = np.abs(self.lateness) * 1e6
            wk = self.work * 1e6
            p = np.percentile(lat, [50, 99])
            w = np.percentile(wk, [50, 99])
            per = self.periods * 1e6
            out.update(period_mean_us=float(per.mean()), period_max_us=float(per.max()),
                       jitter_p50_us=float(p[0]), jitter_p99_us=float(p[1]), jitter_max_us=float(lat.max()),
                       work_p50_us=float(w[0]), work_p99_us=float(w[1]), work_max_us=float(wk.max()))
        return out


@dataclass(frozen=True, slots=True)
class RecordedRows:
    """Rows ``[t, commanded..., measured...]`` (SI) recorded since the last ones, for the open recording file."""

    rows: np.ndarray


@dataclass(frozen=True, slots=True)
class RealtimeStatus:
    """What the loop thread got when it asked for realtime priority (reported by ``status``)."""

    message: str


@dataclass(frozen=True, slots=True)
class StopServer:
    """The daemon stops: the server closes and exits."""


@dataclass(frozen=True, slots=True)
class ServerReady:
    """Server → daemon, once: the server serves, on these endpoints (as bound: a port 0 became a real one)."""

    command_endpoint: str
    telemetry_endpoint: str


#: Loop (and daemon) → server: everything the PAIR socket carries that way.
FromLoop = Reply | Event | StateSnapshot | LoopStatistics | RecordedRows | RealtimeStatus | StopServer


def send_to_server(sock: zmq.Socket, msg: FromLoop, flags: int = 0) -> None:
    """Send one message to the server (``zmq.Again`` with NOBLOCK when its queue is full)."""
    ipc.send(sock, msg, flags)


def recv_from_loop(sock: zmq.Socket, flags: int = 0) -> FromLoop:
    """Receive one message from the loop (``zmq.Again`` with NOBLOCK and nothing waiting)."""
    msg = ipc.recv(sock, flags)
    if not isinstance(msg, FromLoop):
        raise InternalError(f"unexpected message from the loop: {type(msg).__name__}")
    return msg


def send_ready(sock: zmq.Socket, ready: ServerReady) -> None:
    """The server's start-up message to the daemon."""
    ipc.send(sock, ready)


def recv_ready(sock: zmq.Socket) -> ServerReady | None:
    """What the daemon waits for after starting the server process (None: some other message, ignored)."""
    msg = ipc.recv(sock)
    return msg if isinstance(msg, ServerReady) else None
