"""The API server: its own process, serving the ZeroMQ command (ROUTER) and telemetry (PUB) sockets.

It receives, size-checks, decodes and validates every request and compiles clips and frames to arrays, then hands
the control core ready-made commands over the link (:mod:`runtime.ipc`); the core's replies, events, telemetry
snapshots and recorded rows come back over the same link and are formatted, published and written here. Nothing it
does can hold up the control loop: it runs in another process. An ``estop`` also trips the shared e-stop flag
before anything else is done with it, so it reaches the core within one cycle whatever is queued or being parsed.
The show-control inputs a head configures (OSC, sACN, MIDI timecode: :mod:`runtime.inputs`) run on threads of this
process and hand their commands to this thread, which sends them on the same link.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from models import errors as E
from models import protocol as P
from runtime import ipc
from runtime import messages as M
from runtime.config import DaemonConfig, resolve
from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.loop import process_threads
from runtime.requests import LOCAL_OPS, OPS, to_command
from runtime.wire_scan import request_id_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServerSpec:
    """What the server process needs, picklable: the head file, the settings, the channels and the link."""

    head_path: str
    overrides: dict[str, Any]
    channels: ChannelMap
    link: str  # the loop's PAIR endpoint (loop → server: replies, events, state)
    commands: str  # the named pipe the loop reads its commands from (server → loop)
    estop_flag: str  # shared-memory name of the e-stop counter
    safe_speed: float  # [safety] safe_speed: the default speed of a pose
    log_level: int = logging.WARNING
    inline_bytes: int = 32 * 1024  # larger requests are decoded by the decoder process


def decoder_main(spec: ServerSpec, endpoint_in: str, endpoint_out: str) -> None:
    """The decoder process: large requests (clips, stream batches) are decoded, validated and compiled here, so
    the server's own thread stays free to take an e-stop at any moment."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.connect(endpoint_in)
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.connect(endpoint_out)
    parent = os.getppid()
    try:
        while os.getppid() == parent:
            if not pull.poll(200):
                continue
            token, envelope, payload, received = ipc.recv(pull)
            ipc.send(push, ("decoded", token, envelope, received, *_decode(payload, token, spec, received)))
    finally:
        pull.close(0)
        push.close(0)
        ctx.term()


def _decode(payload: bytes, token: int, spec: ServerSpec,
            received: float) -> tuple[Any, str, Any, dict[str, Any] | None]:
    """(request id, op, command or None, error reply or None) for one raw request."""
    rid: Any = None
    try:
        req = M.decode_request(payload)
        rid, op = req.id, type(req).__struct_config__.tag
        if op in LOCAL_OPS:
            raise E.TooLarge(f"a {op} request needs no more than {spec.inline_bytes} bytes")
        return rid, op, to_command(req, token, spec.channels, spec.safe_speed, received), None
    except M.RequestError as exc:
        return exc.request_id, "", None, P.reply_for(exc.request_id, exc)
    except E.LikenessError as exc:
        return rid, "", None, P.reply_for(rid, exc)
    except Exception as exc:
        log.exception("internal error decoding a request")
        return rid, "", None, P.reply_for(rid, exc)


def main(spec: ServerSpec) -> None:
    """Process entry point: serve until the loop process says stop or goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon process stops us
    logging.basicConfig(level=spec.log_level, format="%(asctime)s %(name)s: %(message)s")
    _die_with_parent()
    # The telemetry thread computes between requests; it must hand the GIL to the request thread within 0.5 ms.
    sys.setswitchinterval(0.0005)
    server = Server(spec)
    try:
        server.run()
    finally:
        server.close()


def _raise_request_threads(priority: int) -> str:
    """With ``priority`` > 0, put this process's request thread (the calling one) and ZeroMQ's I/O threads under
    SCHED_FIFO at ``priority``, after every helper process and thread has started (they keep normal scheduling: the
    telemetry thread, the large-request decoder, the show-control inputs). Returns what happened, for the log."""
    if priority <= 0:
        return "API server at normal priority"
    me = threading.get_native_id()
    raised, failed = 0, ""
    threads = process_threads()
    if not threads:
        return "API server at normal priority (no thread list in /proc/self/task)"
    for tid, name in threads.items():
        if tid != me and not name.startswith("ZMQbg/IO"):
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            raised += 1
        except OSError as exc:
            failed = f"; SCHED_FIFO refused ({exc}): needs CAP_SYS_NICE or an rtprio limit"
    msg = f"API server request and I/O threads ({raised}) at SCHED_FIFO {priority}{failed}"
    (log.warning if failed else log.info)("%s", msg)
    return msg


def _die_with_parent() -> None:
    """Ask the kernel to end this process when the daemon dies (Linux), so no server outlives a ``kill -9``."""
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Server:
    def __init__(self, spec: ServerSpec) -> None:
        from models.headspec import load_head
        from runtime.config import daemon_config

        self.spec = spec
        self.head = load_head(spec.head_path)
        self.cfg: DaemonConfig = daemon_config(self.head, spec.overrides)
        self.channels = spec.channels
        self.names = self.head.actuator_names
        self.units = [a.unit for a in self.head.actuators]
        self.inv_scale = 1.0 / np.array([a.unit_scale for a in self.head.actuators])
        self.estop_flag = ipc.EStopFlag(spec.estop_flag)
        self.linkmap = _load_linkmap(self.head)
        self.guard = _load_guard(self.head)  # the full strain check, confirming the loop's reduced one
        self.guard_mismatch = 0
        self.ctx = zmq.Context()
        self.link = self.ctx.socket(zmq.PAIR)
        self.link.setsockopt(zmq.LINGER, 0)
        self.link.connect(spec.link)
        self.to_loop = ipc.PipeWriter(spec.commands)
        self.tokens = itertools.count(1)
        self.pending: dict[int, tuple[list[bytes], Any, str, float]] = {}
        self.stats_summary: dict[str, Any] = {}
        self.realtime = "not started"
        self.recording: dict[str, Any] | None = None
        self.auth: Any = None
        self.router, self.pub = self._bind()
        self._pub_lock = threading.Lock()  # the publish socket is shared by the request and telemetry threads
        self._telemetry = _LatestWorker(self._publish_state, "telemetry")
        self.inputs = _start_inputs(self.head, self.channels, self.ctx, self.estop_flag)
        self._start_decoder()
        _raise_request_threads(self.cfg.runtime.api_priority)  # logs what it did
        ipc.send(self.link, ("ready", self.command_endpoint, self.telemetry_endpoint))

    def _start_decoder(self) -> None:
        import pickle
        import subprocess
        import sys
        import tempfile

        self.tmp = tempfile.mkdtemp(prefix="likeness-api-")
        self.to_decoder = self.ctx.socket(zmq.PUSH)
        self.to_decoder.setsockopt(zmq.LINGER, 0)
        self.to_decoder.bind(f"ipc://{self.tmp}/in")
        self.from_decoder = self.ctx.socket(zmq.PULL)
        self.from_decoder.bind(f"ipc://{self.tmp}/out")
        self.decoder = subprocess.Popen([sys.executable, "-m", "runtime.server", "--decoder", f"ipc://{self.tmp}/in",
                                         f"ipc://{self.tmp}/out"], stdin=subprocess.PIPE)
        assert self.decoder.stdin is not None
        self.decoder.stdin.write(pickle.dumps(self.spec))
        self.decoder.stdin.close()

    # ------------------------------------------------------------------ sockets
    def _bind(self) -> tuple[zmq.Socket, zmq.Socket]:
        api = self.cfg.api
        router = self.ctx.socket(zmq.ROUTER)
        pub = self.ctx.socket(zmq.PUB)
        for sock in (router, pub):
            sock.setsockopt(zmq.LINGER, 0)
        router.setsockopt(zmq.MAXMSGSIZE, api.hard_max_message_bytes)
        router.setsockopt(zmq.ROUTER_MANDATORY, 0)
        router.setsockopt(zmq.SNDHWM, 1000)
        router.setsockopt(zmq.RCVHWM, 1000)
        pub.setsockopt(zmq.SNDHWM, 1000)
        if api.curve_secret_key:
            from zmq.auth import load_certificate
            from zmq.auth.thread import ThreadAuthenticator

            base = self.head.source.parent
            public, secret = load_certificate(str(resolve(base, api.curve_secret_key)))
            if secret is None:
                raise ValueError(f"api.curve_secret_key: {api.curve_secret_key} holds no secret key")
            self.auth = ThreadAuthenticator(self.ctx)
            self.auth.start()
            self.auth.configure_curve(domain="*", location=str(resolve(base, api.curve_allow_dir)))
            for sock in (router, pub):
                sock.curve_secretkey = secret
                sock.curve_publickey = public
                sock.curve_server = True
        if api.allow_remote:
            log.warning("remote clients allowed on %s: %s", api.command, "CURVE authentication with an allow-list"
                        if api.curve_secret_key else "NO authentication, plain text (insecure_remote = true)")
        router.bind(api.command)
        pub.bind(api.telemetry)
        self.command_endpoint = router.getsockopt_string(zmq.LAST_ENDPOINT)
        self.telemetry_endpoint = pub.getsockopt_string(zmq.LAST_ENDPOINT)
        return router, pub

    def close(self) -> None:
        import shutil

        self._telemetry.close()
        if self.recording is not None:  # the daemon stops while recording: the file is complete up to here
            self.recording["writer"].close()
            self.recording = None
        self.decoder.terminate()
        try:
            self.decoder.wait(2.0)
        except Exception:
            self.decoder.kill()
        shutil.rmtree(self.tmp, ignore_errors=True)
        for sock in (self.router, self.pub, self.link, self.to_decoder, self.from_decoder):
            sock.close(0)
        self.to_loop.close()
        if self.auth is not None:
            self.auth.stop()
        if self.inputs is not None:
            self.inputs.close()
        self.ctx.term()
        self.estop_flag.close()

    # ------------------------------------------------------------------ serving
    def run(self) -> None:
        poller = zmq.Poller()
        poller.register(self.router, zmq.POLLIN)
        poller.register(self.link, zmq.POLLIN)
        poller.register(self.from_decoder, zmq.POLLIN)
        if self.inputs is not None:
            poller.register(self.inputs.pull, zmq.POLLIN)
        parent = os.getppid()
        writing = False
        while True:
            if self.to_loop.wants_write != writing:  # watch the pipe only while commands wait for room in it
                writing = self.to_loop.wants_write
                poller.register(self.to_loop.fileno(), zmq.POLLOUT if writing else 0)
            events = dict(poller.poll(200))
            if writing and self.to_loop.fileno() in events:
                try:
                    self.to_loop.flush()
                except BrokenPipeError:
                    return
            if self.link in events and not self._drain_link():
                return
            if self.router in events:
                self._drain_requests()
            if self.from_decoder in events:
                self._drain_decoded()
            if self.inputs is not None and self.inputs.pull in events:
                self._drain_inputs()
            if os.getppid() != parent:
                return

    def _drain_requests(self) -> None:
        # Small requests first: an e-stop queued behind a large request is handled before it is decoded.
        batch = []
        for _ in range(256):
            try:
                batch.append(self.router.recv_multipart(zmq.NOBLOCK))
            except zmq.Again:
                break
        batch.sort(key=lambda fr: len(fr[-1]) if fr else 0)
        for frames in batch:
            self._request(frames, time.monotonic())

    def _request(self, frames: list[bytes], received: float) -> None:
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
            rid = request_id_of(payload)  # when it can be read cheaply
            too_large = E.TooLarge(f"request of {len(payload)} bytes exceeds {limit} bytes")
            self._reply(envelope, P.reply_for(rid, too_large))
            return
        if len(payload) > self.spec.inline_bytes:  # decoded in the decoder process
            ipc.send(self.to_decoder, (next(self.tokens), envelope, payload, received))
            return
        rid: Any = None
        try:
            req = M.decode_request(payload)
            rid, op = req.id, type(req).__struct_config__.tag
            if op == "estop":
                self.estop_flag.trip(getattr(req, "reason", None) or "api")  # reaches the core before the command
            if op in LOCAL_OPS:
                self._reply(envelope, {"id": rid, "ok": True, **self._local(req, received)})
                return
            token = next(self.tokens)
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
        self.pending[token] = (envelope, rid, op, received)
        self._to_core(cmd)

    def _drain_decoded(self) -> None:
        for _ in range(100):
            try:
                _, token, envelope, received, rid, op, cmd, error = ipc.recv(self.from_decoder, zmq.NOBLOCK)
            except zmq.Again:
                return
            if error is not None:
                self._reply(envelope, error)
                continue
            if op == "estop":
                self.estop_flag.trip(getattr(cmd, "reason", None) or "api")
            self.pending[token] = (envelope, rid, op, received)
            self._to_core(cmd)

    def _to_core(self, cmd: Any) -> None:
        """A ready command to the loop, in order; what the pipe cannot take now is written by :meth:`run` later."""
        try:
            self.to_loop.send(("cmd", cmd))
        except BrokenPipeError:
            log.error("the control loop is gone; command dropped")

    def _drain_inputs(self) -> None:
        """Commands from the show-control inputs (OSC, sACN, timecode): a token each, then on to the core."""
        assert self.inputs is not None
        for cmd in self.inputs.drain():
            token = next(self.tokens)
            source = "timecode" if isinstance(cmd, C.Timecode) else getattr(cmd, "source", "osc")  # control: OSC
            self.pending[token] = ([], None, f"input:{source}", getattr(cmd, "received", None) or time.monotonic())
            self._to_core(dataclasses.replace(cmd, token=token))

    def _reply(self, envelope: list[bytes], reply: dict[str, Any]) -> None:
        try:
            self.router.send_multipart([*envelope, P.pack(reply)], zmq.NOBLOCK)
        except zmq.ZMQError as exc:
            log.debug("reply not sent: %s", exc)

    # ------------------------------------------------------------------ local ops
    def _local(self, req: Any, received: float) -> dict[str, Any]:
        if isinstance(req, M.ClockRequest):
            out: dict[str, Any] = {"t_recv": received, "clock": "monotonic"}
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
            "rate_hz": rt.rate_hz, "telemetry": self.telemetry_endpoint, "ops": sorted(OPS),
            "max_message_bytes": self.cfg.api.max_message_bytes, "stream_delay_s": rt.stream_delay_s,
            "clip_memory_bytes": rt.clip_memory_bytes,
            "inputs": {} if self.inputs is None else self.inputs.described(),
        }

    # ------------------------------------------------------------------ from the core
    def _drain_link(self) -> bool:
        for _ in range(1000):
            try:
                kind, *rest = ipc.recv(self.link, zmq.NOBLOCK)
            except zmq.Again:
                return True
            if kind == "stop":
                return False
            if kind == "reply":
                self._core_reply(*rest)
            elif kind == "event":
                self._publish(P.TOPIC_EVENT, rest[0])
            elif kind == "state":  # link poses and the full strain check take ms: off the request thread
                self._telemetry.put(rest[0])
            elif kind == "stats":
                self.stats_summary = _summary(*rest)
            elif kind == "realtime":
                self.realtime = rest[0]
            elif kind == "record" and self.recording is not None:
                self._record_rows(rest[0])
        return True

    def _core_reply(self, token: int, body: dict[str, Any]) -> None:
        entry = self.pending.pop(token, None)
        if entry is None:
            return
        envelope, rid, op, received = entry
        err = body.get("error")
        if op.startswith("input:"):  # an input's command: nobody to answer; a refusal is logged
            if err is not None and self.inputs is not None:
                self.inputs.refused(op[6:], err["code"], err["message"])
            return
        if err is not None:
            self._reply(envelope, P.error_reply(rid, err["code"], err["message"]))
            return
        if op == "stream":
            body["t_recv"] = received  # when the request reached the daemon (its clock), for latency accounting
        try:
            body = self._format(op, body)
        except E.LikenessError as exc:
            self._reply(envelope, P.reply_for(rid, exc))
            return
        self._reply(envelope, {"id": rid, "ok": True, **body})

    def _format(self, op: str, body: dict[str, Any]) -> dict[str, Any]:
        if op == "status":
            out = self._common(body)
            for key in ("estop", "fault", "moving", "timeline", "stream", "recording", "pose_reached", "pose_settled",
                        "extra", "clip_bytes", "guard", "source", "clock", "live"):
                if key in body:
                    out[key] = body[key]
            out["loop"] = self.stats_summary
            out["realtime"] = self.realtime
            if self.inputs is not None:
                out["inputs"] = self.inputs.stats()
            return out
        if op == "pose":
            return {"targets": self._units(body["targets_si"]), "speed": body["speed"]}
        if op == "record":
            if body.get("stopped"):
                return self._finish_recording(body)
            self._start_recording(body["recording"])
            return body
        return body

    def _start_recording(self, name: str) -> None:
        """A crash-safe recording file, streamed as the core hands rows over (``docs/operations.md``)."""
        from runtime.recording import RecordingWriter

        rt = self.cfg.runtime
        base = Path(rt.record_dir)
        path = base / f"{name}.lrec"
        k = 1
        while path.exists():  # never overwrite an earlier recording
            k += 1
            path = base / f"{name}-{k}.lrec"
        writer = RecordingWriter(path, self.names, self.units, {"head": self.head.name, "rate_hz": rt.rate_hz})
        self.recording = {"name": name, "writer": writer, "rows": 0}

    def _record_rows(self, rows: np.ndarray) -> None:
        """Rows [t, commanded..., measured...] (SI) → configured units, appended to the file."""
        rec = self.recording
        assert rec is not None
        n = len(self.names)
        block = np.array(rows, dtype=float)
        block[:, 1:1 + n] *= self.inv_scale
        block[:, 1 + n:] *= self.inv_scale
        rec["writer"].append(block)
        rec["rows"] += len(block)

    def _finish_recording(self, body: dict[str, Any]) -> dict[str, Any]:
        rec, self.recording = self.recording, None
        if rec is None:
            return {"path": None, "samples": 0, "dropped": body["samples"]}
        writer = rec["writer"]
        writer.close()
        path = writer.path
        self._publish(P.TOPIC_EVENT, {"event": "record", "t": time.monotonic(), "state": "saved",
                                      "name": rec["name"], "path": str(path), "samples": rec["rows"]})
        return {"path": str(path.resolve()), "samples": rec["rows"], "dropped": max(0, body["samples"] - rec["rows"])}

    # ------------------------------------------------------------------ telemetry
    def _units(self, si: np.ndarray) -> dict[str, float | None]:
        vals = (np.asarray(si) * self.inv_scale).tolist()
        return {n: (v if math.isfinite(v) else None) for n, v in zip(self.names, vals, strict=True)}

    def _common(self, snap: dict[str, Any]) -> dict[str, Any]:
        return {"t": snap["t"], "lifecycle": snap["lifecycle"], "mode": snap["mode"],
                "commanded": self._units(snap["commanded_si"]), "measured": self._units(snap["measured_si"]),
                "buses": snap["buses"], "connected": snap["connected"], "connection": snap.get("connection", {}),
                "feedback_age_s": snap["feedback_age"]}

    def _state_message(self, snap: dict[str, Any]) -> dict[str, Any]:
        msg = self._common(snap)
        msg["loop"] = self.stats_summary
        for key in ("clip", "stream", "extra", "guard", "source", "clock", "live"):
            if key in snap:
                msg[key] = snap[key]
        measured = snap["measured_si"]
        if self.linkmap is not None and np.isfinite(measured).all():
            msg["links"] = self._link_poses(measured)
        if self.guard is not None and snap["lifecycle"] == "active":
            msg["guard_full"] = self._confirm_guard(snap["t"], snap["commanded_si"])
        return msg

    # Both results below cost about a millisecond each (a full predictor pass; m(p) per link) and the pose they
    # depend on stands still most of the time: each is recomputed only when its pose moved.
    _links_cache: tuple[bytes, dict[str, list[float]]] | None = None
    _guard_cache: tuple[bytes, dict[str, Any]] | None = None

    def _confirm_guard(self, t: float, q: np.ndarray) -> dict[str, Any]:
        """Full strain check of the commanded pose (off the loop): its strain range, and an event when the loop's
        reduced check decided otherwise (once per pose)."""
        key = np.asarray(q, dtype=np.float64).tobytes()
        if self._guard_cache is not None and self._guard_cache[0] == key:
            return {**self._guard_cache[1], "mismatches": self.guard_mismatch}
        strain = self.guard.full(q)
        full_ok = bool(self.guard.passes(strain) and self.guard.in_range(q))
        reduced_ok = bool(self.guard.check(q))
        if full_ok != reduced_ok:
            self.guard_mismatch += 1
            self._publish(P.TOPIC_EVENT, {"event": "skin_guard", "t": t, "full": full_ok, "reduced": reduced_ok,
                                          "strain": [float(strain[0]), float(strain[1])],
                                          "mismatches": self.guard_mismatch})
        out = {"ok": full_ok, "strain": [round(float(strain[0]), 4), round(float(strain[1]), 4)],
               "mismatches": self.guard_mismatch}
        self._guard_cache = (key, out)
        return dict(out)

    def _link_poses(self, q: np.ndarray) -> dict[str, list[float]]:
        """Predicted link poses m(q) at measured actuator values: [x, y, z (m), rx, ry, rz (rotation vector)]."""
        from models.rigid import matrix_to_rotvec

        key = np.asarray(q, dtype=np.float64).tobytes()
        if self._links_cache is not None and self._links_cache[0] == key:
            return self._links_cache[1]
        poses = self.linkmap.poses(dict(zip(self.names, q.tolist(), strict=True)))
        out = {name: [*T[:3, 3].tolist(), *matrix_to_rotvec(T[:3, :3]).tolist()] for name, T in poses.items()}
        self._links_cache = (key, out)
        return out

    def _publish_state(self, snap: dict[str, Any]) -> None:
        self._publish(P.TOPIC_STATE, self._state_message(snap))

    def _publish(self, topic: bytes, msg: dict[str, Any]) -> None:
        data = P.pack(_plain(msg))
        try:
            with self._pub_lock:
                self.pub.send_multipart([topic, data], zmq.NOBLOCK)
        except zmq.Again:
            pass
        except zmq.ZMQError as exc:
            log.warning("telemetry publish failed: %s", exc)


class _LatestWorker:
    """A thread that runs ``work`` on the latest item put, dropping any it had no time for (telemetry snapshots:
    only the newest matters), so slow formatting never delays the requests handled on the calling thread."""

    def __init__(self, work: Any, name: str) -> None:
        self._work = work
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: Any) -> None:
        with self._cond:
            self._item = item
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._item is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                item, self._item = self._item, None
            try:
                self._work(item)
            except Exception:
                log.exception("telemetry failed")


def _plain(obj: Any) -> Any:
    """numpy scalars and arrays → Python values msgpack can carry."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _summary(period: float, n: int, missed: int, skipped: int, lateness: np.ndarray, work: np.ndarray,
             periods: np.ndarray, phase_lock: dict[str, Any] | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"rate_hz": 1.0 / period, "cycles": n, "missed": missed, "skipped": skipped}
    if phase_lock is not None:
        out["stream_phase_lock"] = phase_lock
    k = len(lateness)
    if k:
        lat = np.abs(lateness) * 1e6
        wk = work * 1e6
        p = np.percentile(lat, [50, 99])
        w = np.percentile(wk, [50, 99])
        per = periods * 1e6
        out.update(period_mean_us=float(per.mean()), period_max_us=float(per.max()),
                   jitter_p50_us=float(p[0]), jitter_p99_us=float(p[1]), jitter_max_us=float(lat.max()),
                   work_p50_us=float(w[0]), work_p99_us=float(w[1]), work_max_us=float(wk.max()))
    return out


def _load_guard(head: Any) -> Any:
    from models.strain_guard import StrainGuard

    try:
        return StrainGuard.for_head(head)
    except Exception:
        log.exception("the full skin-strain check is unavailable")
        return None


def _start_inputs(head: Any, channels: ChannelMap, ctx: zmq.Context, estop: ipc.EStopFlag) -> Any:
    """The show-control inputs the head configures (``[inputs]``), started; None when it configures none."""
    from runtime.inputs.config import inputs_config
    from runtime.inputs.hub import InputHub

    cfg = inputs_config(head, channels)
    if not cfg.any:
        return None
    hub = InputHub(cfg, channels, ctx, estop.trip)
    try:
        hub.start()
    except Exception:
        hub.close()
        raise
    return hub


def _load_linkmap(head: Any) -> Any:
    from models.linkmap import LinkMap

    path = head.path("linkmap")
    if path is None or not path.exists():
        return None
    return LinkMap.for_head(head)




if __name__ == "__main__":
    import pickle
    import sys

    spec_in = pickle.loads(sys.stdin.buffer.read())
    if len(sys.argv) == 4 and sys.argv[1] == "--decoder":
        decoder_main(spec_in, sys.argv[2], sys.argv[3])
    else:
        main(spec_in)
