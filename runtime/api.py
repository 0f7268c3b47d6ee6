"""The daemon's command API: the ROUTER socket's serving loop, request validation and one handler per operation.

:class:`CommandApi` is a mixin of :class:`runtime.daemon.Daemon`; handlers validate every field first (errors are
:class:`~runtime.protocol.ProtocolError` replies) and change shared state only under the daemon lock. Operations and
their messages are documented in ``docs/protocol.md``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import zmq

from runtime import protocol as P
from runtime.curves import ClipError, clip_from_dict
from runtime.protocol import Fields, ProtocolError
from runtime.recording import Recorder
from runtime.solve import UnknownChannel

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)

MAX_STREAM_FRAMES_PER_REQUEST = 10_000
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


class CommandApi:
    """Serving and handling of command requests (mixed into the daemon, whose state it uses)."""

    def _serve_api(self) -> None:
        router = self._router
        assert router is not None
        poller = zmq.Poller()
        poller.register(router, zmq.POLLIN)
        limit = self.cfg.api.max_message_bytes
        next_promote = 0.0
        while not self._stop.is_set():
            if self.clock() > next_promote:  # threads created since (bus notifiers after a reset, ...)
                self._promote()
                next_promote = self.clock() + 2.0
            try:
                if not poller.poll(50):
                    continue
                frames = router.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                continue
            except zmq.ZMQError as exc:
                if self._stop.is_set():
                    break
                log.warning("command socket error: %s", exc)
                continue
            received = self.clock()
            if len(frames) < 2:
                continue
            envelope, payload = frames[:-1], frames[-1]
            if len(payload) > limit:
                reply = P.error_reply(None, "too_large", f"request of {len(payload)} bytes exceeds {limit} bytes")
            else:
                reply = self.handle_raw(payload, received)
            try:
                router.send_multipart([*envelope, P.pack(reply)], zmq.NOBLOCK)
            except zmq.ZMQError as exc:
                log.debug("reply not sent: %s", exc)

    def handle_raw(self, payload: bytes, received: float | None = None) -> dict[str, Any]:
        """Decode and handle one request; always returns a reply map, never raises."""
        try:
            msg = P.unpack(payload)
        except ProtocolError as exc:
            return P.error_reply(None, exc.code, exc.message)
        return self.handle(msg, received)

    def handle(self, msg: Any, received: float | None = None) -> dict[str, Any]:
        """Handle one decoded request; always returns a reply map, never raises."""
        rid = P.request_id(msg)
        received = self.clock() if received is None else received
        try:
            if not isinstance(msg, Mapping):
                raise ProtocolError("bad_request", "a request must be a map with 'op' and 'id'")
            op = msg.get("op")
            if not isinstance(op, str):
                raise ProtocolError("bad_request", "field 'op' must be a string")
            if "id" in msg and rid is None:
                raise ProtocolError("bad_request", "field 'id' must be an integer or a string of up to 128 chars")
            handler = self._OPS.get(op)
            if handler is None:
                raise ProtocolError("unknown_op", f"unknown op {op[:40]!r}; known: {', '.join(sorted(self._OPS))}")
            body = handler(self, msg, received)
            return {"id": rid, "ok": True, **body}
        except ProtocolError as exc:
            return P.error_reply(rid, exc.code, exc.message)
        except Exception as exc:  # a bug must never take the daemon down
            log.exception("internal error handling a request")
            return P.error_reply(rid, "internal", f"{type(exc).__name__}: {exc}")

    # ---------------------------------------------------------------- ops
    def _op_hello(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, {"client"})
        from likeness import __version__

        acts = []
        for a in self.head.actuators:
            s = a.unit_scale
            acts.append({"name": a.name, "unit": a.unit, "bus": a.bus, "min": a.min / s, "max": a.max / s,
                         "neutral": a.neutral / s, "max_velocity": a.max_velocity / s,
                         "max_acceleration": a.max_acceleration / s})
        groups = [{"name": g.name, "kind": g.kind, "actuators": list(g.actuators), "gains": list(g.gains)}
                  for g in self.head.groups]
        return {
            "protocol": P.PROTOCOL_VERSION, "daemon": f"likeness {__version__}",
            "head": {"name": self.head.name, "description": self.head.description, "actuators": acts,
                     "groups": groups, "channels": self.solver.channels()},
            "rate_hz": self.cfg.runtime.rate_hz, "telemetry": self.telemetry_endpoint,
            "ops": sorted(self._OPS), "max_message_bytes": self.cfg.api.max_message_bytes,
            "stream_delay_s": self.stream.delay,
        }

    def _op_status(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            now = self.clock()
            out = {
                "t": now, "lifecycle": self.lifecycle, "mode": self.mode, "estop": self.estop_reason,
                "fault": self.fault_info, "buses": {b: s.value for b, s in self.hw.states.items()},
                "commanded": self._units(self.safety.q), "measured": self._units(self.measured),
                "moving": bool(np.any(np.abs(self.safety.v) > 1e-4)),
                "loop": self.stats.summary(), "realtime": self.realtime_status,
                "timeline": self.timeline.describe(now), "stream": self.stream.stats(),
                "recording": None if self.recorder is None else {"name": self.record_name,
                                                                 "samples": self.recorder.count},
            }
            if self.mode == "pose" and self.pose_target is not None:
                err = np.abs(self.pose_target - self.safety.q)
                out["pose_reached"] = bool(np.all(err < 1e-6) and not out["moving"])
            if self.extra:
                out["extra"] = self.extra
        return out

    def _op_enable(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.enable()
        return {"lifecycle": self.lifecycle}

    def _op_disable(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.disable()
        return {"lifecycle": self.lifecycle}

    def _op_estop(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"reason"})
        self.estop(f.string("reason", "api", max_len=200))
        return {"lifecycle": self.lifecycle}

    def _op_reset(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.reset()
        return {"lifecycle": self.lifecycle}

    def _op_clock(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"t_client"})
        out: dict[str, Any] = {"t_recv": now, "clock": "monotonic"}
        if f.has("t_client"):
            out["t_client"] = f.number("t_client")
        out["t_send"] = self.clock()
        return out

    def _check_channels(self, channels: Iterable[str]) -> None:
        try:
            self.solver.check_channels(channels)
        except UnknownChannel as exc:
            raise ProtocolError("unknown_channel", f"unknown channel {str(exc.args[0])[:128]!r}; known: "
                                f"{', '.join(sorted(self.solver.channels()))}") from None

    def _op_load_clip(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"clip"})
        try:
            clip = clip_from_dict(f.mapping("clip"))
        except ClipError as exc:
            raise ProtocolError("bad_value", str(exc)) from None
        self._check_channels(clip.channels)
        with self._lock:
            try:
                self.timeline.load(clip)
            except ClipError as exc:
                raise ProtocolError("too_large", str(exc)) from None
        return {"clip": clip.name, "duration": clip.duration, "channels": sorted(clip.channels),
                "keys": clip.key_count()}

    def _op_play(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"clip", "at", "from", "speed", "loop"})
        name = f.string("clip")
        at = f.number("at", None, lo=now - 3600, hi=now + 3600) if f.has("at") else None
        offset = f.number("from", 0.0, lo=-3600, hi=86400)
        speed = f.number("speed", 1.0, lo=0.01, hi=10.0)
        loop = f.boolean("loop", False)
        with self._lock:
            self._require_active("play")
            if name not in self.timeline.clips:
                raise ProtocolError("not_found", f"no clip {name!r} loaded; loaded: {sorted(self.timeline.clips)}")
            self.stream.clear()
            start = self.timeline.play(name, self.clock(), at, offset, speed, loop)
            self._clip_done_reported = False
            self._set_mode("clip")
            self._event("clip", state="playing", clip=name, start=start)
            return {"clip": name, "start": start, "duration": self.timeline.clips[name].duration}

    def _op_pause(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._require_active("pause")
            self.timeline.pause(self.clock())
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_resume(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._require_active("resume")
            if self.timeline.playback is None:
                raise ProtocolError("bad_state", "nothing to resume: no clip is playing")
            self.timeline.resume(self.clock())
            self._set_mode("clip")
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_stop(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._stop_motion()
        return {"mode": self.mode}

    def _op_seek(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"time"})
        t = f.number("time", lo=-3600, hi=86400)
        with self._lock:
            self._require_active("seek")
            if self.timeline.playback is None:
                raise ProtocolError("bad_state", "nothing to seek: no clip is playing")
            self.timeline.seek(self.clock(), t)
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_stream(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"channels", "frames"})
        channels = f.array("channels", 256)
        if not channels or not all(isinstance(c, str) and 0 < len(c) <= 128 for c in channels):
            raise ProtocolError("bad_request", "field 'channels' must be a non-empty array of channel names")
        if len(set(channels)) != len(channels):
            raise ProtocolError("bad_request", "field 'channels' lists a channel twice")
        self._check_channels(channels)
        frames = f.array("frames", MAX_STREAM_FRAMES_PER_REQUEST)
        width = len(channels) + 1
        parsed: list[tuple[float, dict[str, float]]] = []
        for j, fr in enumerate(frames):
            if not isinstance(fr, list) or len(fr) != width:
                raise ProtocolError("bad_request", f"frames[{j}] must be [t, {len(channels)} values]")
            vals = [P.finite_number(x, f"frames[{j}][{k}]") for k, x in enumerate(fr)]
            parsed.append((vals[0], dict(zip(channels, vals[1:], strict=True))))
        with self._lock:
            self._require_active("stream")
            if self.mode != "stream":
                self.timeline.stop()
                self.stream.clear()
                self._set_mode("stream")
            now = self.clock()
            counts = {"ok": 0, "late": 0, "ahead": 0, "full": 0}
            for t, values in parsed:
                counts[self.stream.push(now, t, values)] += 1
            if counts["late"]:
                self._event("dropped_frames", late=counts["late"], total=self.stream.late)
            return {"accepted": counts["ok"], "late": counts["late"], "ahead": counts["ahead"],
                    "full": counts["full"], "buffered": len(self.stream), "t": now}

    def _op_pose(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"pose", "speed"})
        pose = f.mapping("pose")
        if not pose or len(pose) > 256:
            raise ProtocolError("bad_request", "field 'pose' must map 1..256 channels to values")
        values = {}
        for ch, v in pose.items():
            if not isinstance(ch, str):
                raise ProtocolError("bad_request", "pose channel names must be strings")
            values[ch] = P.finite_number(v, f"pose[{ch[:64]!r}]")
        self._check_channels(values)
        speed = f.number("speed", self.cfg.safety.safe_speed, lo=0.01, hi=1.0)
        with self._lock:
            self._require_active("pose")
            res = self.solver.solve(values, self.safety.commands())
            if res.extra:
                self.extra = res.extra
            base = self.pose_target if self.mode == "pose" and self.pose_target is not None else self.safety.q
            x = self.safety.vector(res.actuators)
            target = self.safety.constrain(np.where(np.isfinite(x), x, base))
            self.timeline.stop()
            self.stream.clear()
            self.pose_target = target
            self.pose_speed = speed
            self._set_mode("pose")
            return {"targets": self._units(target), "speed": speed}

    def _op_record(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"action", "name"})
        action = f.string("action")
        if action == "start":
            name = f.string("name", "recording", max_len=64)
            if not _RECORD_NAME.match(name):
                raise ProtocolError("bad_value", "record name: letters, digits, _ . - only (max 64)")
            rt = self.cfg.runtime
            capacity = int(rt.record_max_s * rt.rate_hz) + 1
            recorder = Recorder(self.names, self.units, self._scale, capacity,
                                {"head": self.head.name, "rate_hz": rt.rate_hz})
            with self._lock:
                if self.recorder is not None:
                    raise ProtocolError("bad_state", f"already recording {self.record_name!r}")
                self.recorder = recorder
                self.record_name = name
                self._event("record", state="started", name=name)
            return {"recording": name}
        if action == "stop":
            with self._lock:
                if self.recorder is None:
                    raise ProtocolError("bad_state", "not recording")
                return self._finish_recording()
        raise ProtocolError("bad_value", f"field 'action' must be 'start' or 'stop' (got {action[:32]!r})")

    def _finish_recording(self) -> dict[str, Any]:
        rec, name = self.recorder, self.record_name
        self.recorder = self.record_name = None
        assert rec is not None and name is not None
        path = Path(self.cfg.runtime.record_dir) / f"{name}.npz"
        rec.save(path)
        self._event("record", state="stopped", name=name, path=str(path), samples=rec.count)
        self._rearm = True
        return {"path": str(path.resolve()), "samples": rec.count, "dropped": rec.dropped}

    _OPS: ClassVar[dict[str, Callable[[Any, Mapping[str, Any], float], dict[str, Any]]]] = {
        "hello": _op_hello, "status": _op_status, "enable": _op_enable, "disable": _op_disable,
        "estop": _op_estop, "reset": _op_reset, "clock": _op_clock, "load_clip": _op_load_clip,
        "play": _op_play, "pause": _op_pause, "resume": _op_resume, "stop": _op_stop, "seek": _op_seek,
        "stream": _op_stream, "pose": _op_pose, "record": _op_record,
    }
