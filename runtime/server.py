"""The API server: its own process, serving the ZeroMQ command (ROUTER) and telemetry (PUB) sockets.

It receives, size-checks, decodes and validates every request and compiles clips and frames to arrays, then hands
the control core ready-made commands over the command pipe (:class:`runtime.ipc.PipeWriter` of
:data:`runtime.loop_messages.ToLoop`); the core's replies, events, telemetry snapshots and recorded rows come back
as :data:`runtime.loop_messages.FromLoop` and are formatted, published (:mod:`runtime.telemetry`) and written
(:mod:`runtime.recording_session`) here. Requests over ``inline_bytes`` are decoded in a process of their own
(:mod:`runtime.decoder`). Nothing it does can hold up the control loop: it runs in another process. An ``estop``
also trips the shared e-stop flag before anything else is done with it, so it reaches the core within one cycle
whatever is queued or being parsed. The show-control inputs a head configures (OSC, sACN, MIDI timecode:
:mod:`runtime.inputs`) run on threads of this process and write their commands to the same pipe from their own
threads (:meth:`Server.forward`; one lock keeps every message on the pipe whole and in order), so a packet wakes
one thread of this process on its way to the loop, not two.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import zmq

from models import errors as E
from models import protocol as P
from runtime import ipc
from runtime import loop_messages as L
from runtime import messages as M
from runtime.client_sockets import ClientSockets, bind_client_sockets
from runtime.config import DaemonConfig
from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.core.events import Body
from runtime.decoder import DecodeJob, DecoderProcess, DecoderSpec, ReplyMap, die_with_parent
from runtime.recording_session import RecordingSession
from runtime.requests import LocalRequest, to_command
from runtime.rtbudget import RealtimeBudget
from runtime.strain_check import FullStrainCheck
from runtime.telemetry import ActuatorUnits, Telemetry
from runtime.wire_scan import RequestId, request_id_of

if TYPE_CHECKING:
    from models.headspec import HeadSpec
    from runtime.inputs.hub import InputHub

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServerSpec:
    """What the server process needs, picklable: the head file, the settings, the channels and the loop's ends."""

    head_path: str
    overrides: dict[str, object]
    channels: ChannelMap
    loop_endpoint: str  # the loop's PAIR endpoint (loop → server: runtime.loop_messages.FromLoop)
    command_pipe: str  # the named pipe the loop reads its commands from (server → loop)
    estop_flag: str  # shared-memory name of the e-stop counter
    safe_speed: float  # [safety] safe_speed: the default speed of a pose
    log_level: int = logging.WARNING
    inline_bytes: int = 32 * 1024  # larger requests are decoded by the decoder process
    strain_check: FullStrainCheck | None = None  # telemetry's full strain check (the daemon's guard's arrays)


#: ``sys.setswitchinterval`` in the API server process: at 0.5 ms a show-control packet waited for the GIL behind the
#: telemetry thread's formatting (send → input thread p50 0.65-0.9 ms at 500 Hz, 0.2 ms with telemetry at 2 Hz).
SERVER_SWITCH_INTERVAL_S = 0.0001


def main(spec: ServerSpec) -> None:
    """Process entry point: serve until the loop process says stop or goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon process stops us
    logging.basicConfig(level=spec.log_level, format="%(asctime)s %(name)s: %(message)s")
    die_with_parent()
    # The telemetry thread computes between requests; it must hand the GIL to the request thread and to the
    # show-control inputs' threads within SERVER_SWITCH_INTERVAL_S.
    sys.setswitchinterval(SERVER_SWITCH_INTERVAL_S)
    server = Server(spec)
    try:
        server.run()
    finally:
        server.close()


#: Share of one CPU the API server process may take at realtime priority (``[runtime] api_priority``), all its threads
#: together, per ``runtime.rtbudget.WINDOW_S``; past it the process runs at normal scheduling for the rest of the
#: window. The sample head's server takes about 15 % of a core at 500 Hz with telemetry at 50 Hz, and 24-30 % with a
#: steady sACN sender at 500 Hz besides: at a share of 30 % it ran out in a third of the windows, and a packet that
#: came then waited behind the emulators for up to 6 ms before it reached the loop.
SERVER_SHARE = 0.5


def server_budget(api_priority: int) -> RealtimeBudget | None:
    """The API server process's realtime budget: every thread (requests, telemetry, the show-control inputs) at
    SCHED_FIFO ``api_priority`` within :data:`SERVER_SHARE` of a core; None with 0 (normal scheduling, the inputs'
    receive threads each within a budget of their own at ``inputs_priority``). One budget for all: an input thread
    under SCHED_FIFO alone waited for the interpreter lock behind the request or telemetry thread, which a busy host
    had preempted while it held the lock (a priority inversion through the lock)."""
    return RealtimeBudget(api_priority, share=SERVER_SHARE, whole_process=True) if api_priority > 0 else None


@dataclass(frozen=True)
class Pending:
    """A command handed to the core, waiting for its reply: whom to answer (a client's envelope and request id, or
    the show-control ``input`` that sent it, which nobody answers), its op, and when it reached the daemon."""

    envelope: list[bytes]
    request_id: RequestId | None
    op: str
    received: float
    input: str | None = None


class PendingRequests:
    """Commands on their way to the core, by the token their reply will carry."""

    def __init__(self) -> None:
        self._tokens = itertools.count(1)
        self._by_token: dict[int, Pending] = {}
        self._standing: dict[str, int] = {}  # a show-control input's token for its quiet commands
        self._standing_input: dict[int, Pending] = {}

    def token(self) -> int:
        """A fresh token for the next command."""
        return next(self._tokens)

    def standing(self, source: str) -> int:
        """The one token of every quiet command of the input ``source`` (the core answers those only to refuse
        them; the answer names the input by it and leaves it standing)."""
        token = self._standing.get(source)
        if token is None:
            token = self._standing[source] = self.token()
            self._standing_input[token] = Pending([], None, f"input:{source}", 0.0, input=source)
        return token

    def add(self, token: int, pending: Pending) -> None:
        self._by_token[token] = pending

    def pop(self, token: int) -> Pending | None:
        entry = self._by_token.pop(token, None)
        return self._standing_input.get(token) if entry is None else entry


class Server:
    """Serves one head's clients: requests in, commands to the loop, replies and telemetry out."""

    to_loop: ipc.PipeWriter[L.ToLoop]  # the command pipe (server → loop)
    from_loop: zmq.Socket  # PAIR: runtime.loop_messages.FromLoop (loop → server)
    clients: ClientSockets  # ROUTER (requests) and PUB (telemetry)
    decoder: DecoderProcess  # large requests
    telemetry: Telemetry
    pending: PendingRequests  # commands on their way to the core, by token
    recording: RecordingSession | None  # the open recording file

    def __init__(self, spec: ServerSpec) -> None:
        from models.headspec import load_head
        from runtime.config import daemon_config

        self.spec = spec
        self.head = load_head(spec.head_path)
        self.cfg: DaemonConfig = daemon_config(self.head, spec.overrides)
        self.channels = spec.channels
        self.units = ActuatorUnits.of(self.head)
        self.estop_flag = ipc.EStopFlag(spec.estop_flag)
        self.ctx = zmq.Context()
        self.from_loop = self.ctx.socket(zmq.PAIR)
        self.from_loop.setsockopt(zmq.LINGER, 0)
        self.from_loop.connect(spec.loop_endpoint)
        self.to_loop = ipc.PipeWriter[L.ToLoop](spec.command_pipe)
        self._pipe_lock = threading.Lock()  # the pipe is written by this thread and by the inputs' threads
        self.pending = PendingRequests()
        self.recording = None
        self.clients = bind_client_sockets(self.ctx, self.head, self.cfg)
        self.telemetry = Telemetry(self.clients.pub, self.head, self.units, spec.strain_check)
        rt = self.cfg.runtime
        self.budget = server_budget(rt.api_priority if rt.realtime else 0)
        self.inputs = _start_inputs(self.head, self.channels, self.ctx, self.estop_flag, self.forward,
                                    self.budget or (rt.inputs_priority if rt.realtime else 0))
        self.decoder = DecoderProcess(self.ctx, DecoderSpec(spec.channels, spec.safe_speed, spec.inline_bytes))
        if self.budget is not None:  # every thread started by now (the inputs' raise those they started)
            log.info("API server process at %s within a CPU budget", self.budget.enter())
        L.send_ready(self.from_loop, L.ServerReady(self.clients.command_endpoint, self.clients.telemetry_endpoint))

    def close(self) -> None:
        if self.inputs is not None:  # first: their threads write to the command pipe
            self.inputs.close()
            self.inputs = None
        self.telemetry.close()
        if self.recording is not None:  # the daemon stops while recording: the file is complete up to here
            self.recording.close()
            self.recording = None
        self.decoder.close()
        self.clients.close()
        self.from_loop.close(0)
        self.to_loop.close()
        self.ctx.term()
        self.estop_flag.close()

    # ------------------------------------------------------------------ serving
    def run(self) -> None:
        """Serve until the loop says stop, the command pipe breaks or the daemon process goes away."""
        poller = zmq.Poller()
        poller.register(self.clients.router, zmq.POLLIN)
        poller.register(self.from_loop, zmq.POLLIN)
        poller.register(self.decoder.results, zmq.POLLIN)
        if self.inputs is not None:
            poller.register(self.inputs.pull, zmq.POLLIN)
        parent = os.getppid()
        writing = False
        while True:
            if self.to_loop.wants_write != writing:  # watch the pipe only while commands wait for room in it
                writing = self.to_loop.wants_write
                poller.register(self.to_loop.fileno(), zmq.POLLOUT if writing else 0)
            if self.budget is not None:
                self.budget.rearm()
            events = dict(poller.poll(200))
            if writing and self.to_loop.fileno() in events:
                try:
                    with self._pipe_lock:
                        self.to_loop.flush()
                except BrokenPipeError:
                    return
            if self.from_loop in events and not self._drain_loop():
                return
            if self.clients.router in events:
                self._drain_requests()
            if self.decoder.results in events:
                self._drain_decoded()
            if self.inputs is not None and self.inputs.pull in events:
                self._drain_inputs()
            if self.budget is not None:
                self.budget.spent()  # over its CPU budget: normal scheduling for the rest of the window
            if os.getppid() != parent:
                return

    def _drain_requests(self) -> None:
        # Small requests first: an e-stop queued behind a large request is handled before it is decoded.
        batch = []
        for _ in range(256):
            try:
                batch.append(self.clients.router.recv_multipart(zmq.NOBLOCK))
            except zmq.Again:
                break
        batch.sort(key=lambda fr: len(fr[-1]) if fr else 0)
        for frames in batch:
            self._request(frames, time.monotonic())

    def _request(self, frames: list[bytes], received: float) -> None:
        """One client request: refused, answered here (hello, clock), sent to the decoder, or to the core."""
        if len(frames) < 2:
            return
        # The only envelopes: [identity, request] (DEALER) or [identity, b"", request] (REQ). Anything else is
        # refused, answered to the identity alone, never echoed.
        if not (len(frames) == 2 or (len(frames) == 3 and frames[1] == b"")):
            size = sum(len(f) for f in frames[1:])
            self._reply(frames[:1], P.reply_for(None, E.BadRequest(f"a request is one frame; got "
                                                                   f"{len(frames) - 1} frames ({size} bytes)")))
            return
        envelope, payload = frames[:-1], frames[-1]
        limit = self.cfg.api.max_message_bytes
        if len(payload) > limit:
            too_large = E.TooLarge(f"request of {len(payload)} bytes exceeds {limit} bytes")
            self._reply(envelope, P.reply_for(request_id_of(payload), too_large))  # the id when cheaply read
            return
        if len(payload) > self.spec.inline_bytes:  # decoded in the decoder process
            self.decoder.submit(DecodeJob(self.pending.token(), envelope, payload, received))
            return
        rid: RequestId | None = None
        try:
            req = M.decode_request(payload)
            rid, op = req.id, type(req).__struct_config__.tag
            if isinstance(req, M.EStopRequest):
                self.estop_flag.trip(req.reason or "api")  # reaches the core before the command
            if isinstance(req, LocalRequest):
                self._reply(envelope, {"id": rid, "ok": True, **self._local(req, received)})
                return
            token = self.pending.token()
            cmd = to_command(req, token, self.channels, self.cfg.safety.safe_speed, received)
        except M.RequestError as exc:
            self._reply(envelope, P.reply_for(exc.request_id, exc))
            return
        except E.LikenessError as exc:
            self._reply(envelope, P.reply_for(rid, exc))
            return
        except Exception as exc:  # a bug must never take the server down
            log.exception("internal error handling a request")
            self._reply(envelope, P.reply_for(rid, exc))
            return
        self.pending.add(token, Pending(envelope, rid, op, received))
        self._to_core(cmd)

    def _drain_decoded(self) -> None:
        for done in self.decoder.drain():
            if done.command is None:
                if done.error is not None:
                    self._reply(done.envelope, done.error)
                continue
            if isinstance(done.command, C.EStop):
                self.estop_flag.trip(done.command.reason or "api")
            self.pending.add(done.token, Pending(done.envelope, done.request_id, done.op, done.received))
            self._to_core(done.command)

    def _to_core(self, cmd: L.ToLoop) -> None:
        """A ready command to the loop, in order; what the pipe cannot take now is written by :meth:`run` later."""
        try:
            with self._pipe_lock:
                self.to_loop.send(cmd)
        except BrokenPipeError:
            log.error("the control loop is gone; command dropped")

    def forward(self, cmd: C.Command) -> bool:
        """A show-control input's command, on the input's thread: a token, then on to the core at once. False when
        part of it waits for room in the pipe (the input hub then wakes :meth:`run`, which writes the rest)."""
        self._to_core(self._tokened(cmd))
        return not self.to_loop.wants_write

    def _drain_inputs(self) -> None:
        """Commands from the show-control inputs (OSC, sACN, timecode): a token each, then on to the core."""
        assert self.inputs is not None
        for cmd in self.inputs.drain():
            self._to_core(self._tokened(cmd))

    def _tokened(self, cmd: C.Command) -> C.Command:
        """An input's command with its token. A live packet goes quiet (the core answers it only when refused) under
        its input's one standing token, so nothing is kept per packet; any other waits for its reply as a request
        does."""
        source, received = _input_origin(cmd)
        if isinstance(cmd, C.Live):
            return dataclasses.replace(cmd, token=self.pending.standing(source), quiet=True)
        token = self.pending.token()
        self.pending.add(token, Pending([], None, f"input:{source}", received, input=source))
        return dataclasses.replace(cmd, token=token)

    def _reply(self, envelope: list[bytes], reply: ReplyMap) -> None:
        try:
            self.clients.router.send_multipart([*envelope, P.pack(reply)], zmq.NOBLOCK)
        except zmq.ZMQError as exc:
            log.debug("reply not sent: %s", exc)

    # ------------------------------------------------------------------ local ops
    def _local(self, req: LocalRequest, received: float) -> ReplyMap:
        """The answer to ``clock`` (this daemon's clock) or ``hello`` (the head, its channels, the limits)."""
        if isinstance(req, M.ClockRequest):
            out: ReplyMap = {"t_recv": received, "clock": "monotonic"}
            if req.t_client is not None:
                out["t_client"] = req.t_client
            out["t_send"] = time.monotonic()
            return out
        from likeness import __version__

        acts = []
        for a in self.head.actuators:
            s = a.unit_scale
            acts.append({"name": a.name, "unit": a.unit, "bus": a.bus, "min": a.min / s, "max": a.max / s,
                         "neutral": a.neutral / s, "max_velocity": a.max_velocity / s,
                         "max_acceleration": a.max_acceleration / s})
        groups = [{"name": g.name, "kind": g.kind, "actuators": list(g.actuators), "gains": list(g.gains)}
                  for g in self.head.groups]
        rt = self.cfg.runtime
        return {
            "protocol": P.PROTOCOL_VERSION, "daemon": f"likeness {__version__}",
            "head": {"name": self.head.name, "description": self.head.description, "actuators": acts,
                     "groups": groups, "channels": self.channels.described()},
            "rate_hz": rt.rate_hz, "telemetry": self.clients.telemetry_endpoint, "ops": sorted(M.OPS),
            "max_message_bytes": self.cfg.api.max_message_bytes, "stream_delay_s": rt.stream_delay_s,
            "clip_memory_bytes": rt.clip_memory_bytes,
            "inputs": {} if self.inputs is None else self.inputs.described(),
        }

    # ------------------------------------------------------------------ from the core
    def _drain_loop(self) -> bool:
        """Handle what the loop sent; False when it said stop."""
        for _ in range(1000):
            try:
                msg = L.recv_from_loop(self.from_loop, zmq.NOBLOCK)
            except zmq.Again:
                return True
            match msg:
                case L.StopServer():
                    return False
                case L.Reply(token, body):
                    self._core_reply(token, body)
                case L.Event(body):
                    self.telemetry.event(body)
                case L.StateSnapshot(body):  # attachment-link poses and the full strain check take ms: off this thread
                    self.telemetry.state(body)
                case L.LoopStatistics():
                    self.telemetry.loop = msg.summary()
                case L.RealtimeStatus(message):
                    self.telemetry.realtime = message
                case L.RecordedRows(rows):
                    if self.recording is not None:
                        self.recording.append(rows, self.units)
        return True

    def _core_reply(self, token: int, body: Body) -> None:
        entry = self.pending.pop(token)
        if entry is None:
            return
        err = body.get("error")
        if entry.input is not None:  # an input's command: nobody to answer; a refusal is logged
            if isinstance(err, dict) and self.inputs is not None:
                self.inputs.refused(entry.input, err["code"], err["message"])
            return
        if isinstance(err, dict):
            self._reply(entry.envelope, P.error_reply(entry.request_id, err["code"], err["message"]))
            return
        if entry.op == "stream":
            body["t_recv"] = entry.received  # when the request reached the daemon (its clock), for latency
        try:
            body = self._format(entry.op, body)
        except E.LikenessError as exc:
            self._reply(entry.envelope, P.reply_for(entry.request_id, exc))
            return
        self._reply(entry.envelope, {"id": entry.request_id, "ok": True, **body})

    def _format(self, op: str, body: Body) -> Body:
        """The core's reply body as clients read it: configured units, the server's own parts of ``status``."""
        if op == "status":
            out = self.telemetry.status(body)
            if self.inputs is not None:
                out["inputs"] = self.inputs.stats()
            return out
        if op == "pose":
            return {"targets": self.units.named(body["targets_si"]), "speed": body["speed"]}
        if op == "record":
            if body.get("stopped"):
                return self._finish_recording(body)
            self._start_recording(str(body["recording"]))
            return body
        return body

    def _start_recording(self, name: str) -> None:
        """A crash-safe recording file, streamed as the core hands rows over (``docs/operations.md``)."""
        rt = self.cfg.runtime
        self.recording = RecordingSession.open(rt.record_dir, name, self.units,
                                               {"head": self.head.name, "rate_hz": rt.rate_hz})

    def _finish_recording(self, body: Body) -> Body:
        rec, self.recording = self.recording, None
        samples = cast(int, body["samples"])  # the rows the core recorded
        if rec is None:
            return {"path": None, "samples": 0, "dropped": samples}
        path = rec.close()
        self.telemetry.event({"event": "record", "t": time.monotonic(), "state": "saved", "name": rec.name,
                              "path": str(path), "samples": rec.rows})
        return {"path": str(path.resolve()), "samples": rec.rows, "dropped": max(0, samples - rec.rows)}


def _input_origin(cmd: C.Command) -> tuple[str, float]:
    """Which show-control input sent ``cmd`` (OSC's control messages say none: "osc"), and when it arrived."""
    now = time.monotonic()
    match cmd:
        case C.Timecode():
            return "timecode", cmd.received or now
        case C.Live():
            return cmd.source, cmd.received or now
        case C.Play():
            return cmd.source, now
    return "osc", now


def _start_inputs(head: HeadSpec, channels: ChannelMap, ctx: zmq.Context, estop: ipc.EStopFlag,
                  forward: Callable[[C.Command], bool] | None = None,
                  priority: int | RealtimeBudget = 0) -> InputHub | None:
    """The show-control inputs the head configures (``[inputs]``), started, handing their commands to ``forward``
    (None: queued for :meth:`InputHub.drain`), their receive threads at SCHED_FIFO ``priority`` within a CPU budget
    each, or within the process's budget when given one (:mod:`runtime.rtbudget`; 0: normal scheduling); None when
    it configures none."""
    from runtime.inputs.config import inputs_config
    from runtime.inputs.hub import InputHub

    cfg = inputs_config(head, channels)
    if not cfg.any:
        return None
    hub = InputHub(cfg, channels, ctx, estop.trip, forward, priority)
    try:
        hub.start()
    except Exception:
        hub.close()
        raise
    return hub


if __name__ == "__main__":
    import pickle

    # The spec's classes are this module's under its own name (not ``__main__``), as the daemon pickles them.
    from runtime.server import main as _main

    _main(pickle.loads(sys.stdin.buffer.read()))
