"""Requests → ready-made core commands: field validation, channel lookup, clip compilation (API server side).

Everything here runs in the API server's process, off the control path. :func:`to_command` turns one decoded request
into a :mod:`runtime.core.commands` command, or raises :class:`~runtime.protocol.ProtocolError` with the documented
code; ``hello`` and ``clock`` are answered by the server itself.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from runtime import protocol as P
from runtime.core import commands as C
from runtime.core.channels import ChannelMap, UnknownChannel
from runtime.core.clips import bind_clip
from runtime.curves import ClipError, clip_from_dict
from runtime.protocol import Fields, ProtocolError

MAX_STREAM_FRAMES_PER_REQUEST = 10_000
RECORD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
LOCAL_OPS = ("hello", "clock")


def check_channels(channels: ChannelMap, names: list[str] | tuple[str, ...]) -> np.ndarray:
    try:
        return channels.indices(names)
    except UnknownChannel as exc:
        raise ProtocolError("unknown_channel", f"unknown channel {str(exc.args[0])[:128]!r}; known: "
                            f"{', '.join(channels.names)}") from None


def to_command(msg: Mapping[str, Any], token: int, channels: ChannelMap, safe_speed: float) -> C.Command:
    """The core command for a decoded request (``op`` known and not local)."""
    op = msg["op"]
    if op in ("enable", "disable", "reset", "status", "pause", "resume", "stop"):
        Fields(msg, set())
        return _SIMPLE[op](token)
    if op == "estop":
        f = Fields(msg, {"reason"})
        return C.EStop(token, f.string("reason", "api", max_len=200))
    if op == "load_clip":
        f = Fields(msg, {"clip"})
        try:
            clip = clip_from_dict(f.mapping("clip"))
        except ClipError as exc:
            raise ProtocolError("bad_value", str(exc)) from None
        check_channels(channels, tuple(clip.channels))
        bound = bind_clip(clip, channels)
        return C.LoadClip(token, bound, bound.key_count, bound.nbytes)
    if op == "unload_clip":
        f = Fields(msg, {"clip"})
        return C.UnloadClip(token, f.string("clip"))
    if op == "play":
        f = Fields(msg, {"clip", "at", "from", "speed", "loop"})
        name = f.string("clip")
        at = f.number("at") if f.has("at") else None
        return C.Play(token, name, at, f.number("from", 0.0, lo=-3600, hi=86400),
                      f.number("speed", 1.0, lo=0.01, hi=10.0), f.boolean("loop", False))
    if op == "seek":
        f = Fields(msg, {"time"})
        return C.Seek(token, f.number("time", lo=-3600, hi=86400))
    if op == "stream":
        return _stream(msg, token, channels)
    if op == "pose":
        f = Fields(msg, {"pose", "speed"})
        pose = f.mapping("pose")
        if not pose or len(pose) > 256:
            raise ProtocolError("bad_request", "field 'pose' must map 1..256 channels to values")
        names, values = [], []
        for ch, v in pose.items():
            if not isinstance(ch, str):
                raise ProtocolError("bad_request", "pose channel names must be strings")
            names.append(ch)
            values.append(P.finite_number(v, f"pose[{ch[:64]!r}]"))
        idx = check_channels(channels, names)
        speed = f.number("speed", safe_speed, lo=0.01, hi=1.0)
        return C.Pose(token, idx, np.array(values), speed)
    if op == "record":
        f = Fields(msg, {"action", "name"})
        action = f.string("action")
        if action == "start":
            name = f.string("name", "recording", max_len=64)
            if not RECORD_NAME.match(name):
                raise ProtocolError("bad_value", "record name: letters, digits, _ . - only (max 64)")
            return C.Record(token, "start", name)
        if action == "stop":
            return C.Record(token, "stop", "")
        raise ProtocolError("bad_value", f"field 'action' must be 'start' or 'stop' (got {action[:32]!r})")
    raise ProtocolError("unknown_op", f"unknown op {str(op)[:40]!r}; known: {', '.join(sorted(OPS))}")


def _stream(msg: Mapping[str, Any], token: int, channels: ChannelMap) -> C.Stream:
    f = Fields(msg, {"channels", "frames"})
    names = f.array("channels", 256)
    if not names or not all(isinstance(c, str) and 0 < len(c) <= 128 for c in names):
        raise ProtocolError("bad_request", "field 'channels' must be a non-empty array of channel names")
    if len(set(names)) != len(names):
        raise ProtocolError("bad_request", "field 'channels' lists a channel twice")
    idx = check_channels(channels, names)
    frames = f.array("frames", MAX_STREAM_FRAMES_PER_REQUEST)
    width = len(names) + 1
    rows = np.empty((len(frames), width))
    for j, fr in enumerate(frames):
        if not isinstance(fr, list) or len(fr) != width:
            raise ProtocolError("bad_request", f"frames[{j}] must be [t, {len(names)} values]")
        rows[j] = [P.finite_number(x, f"frames[{j}][{k}]") for k, x in enumerate(fr)]
    return C.Stream(token, rows[:, 0].copy(), idx, rows[:, 1:].copy())


_SIMPLE = {"enable": C.Enable, "disable": C.Disable, "reset": C.Reset, "status": C.Status, "pause": C.Pause,
           "resume": C.Resume, "stop": C.StopMotion}
OPS = (*LOCAL_OPS, "status", "enable", "disable", "estop", "reset", "load_clip", "unload_clip", "play", "pause",
       "resume", "stop", "seek", "stream", "pose", "record")
