"""Typed requests → ready-made core commands: channel lookup and clip compilation (API server side).

Requests are decoded and validated in one pass by :func:`runtime.messages.decode_request` (msgspec Structs, each
named after the core command it becomes: ``EStopRequest`` → :class:`runtime.core.commands.EStop`);
:func:`to_command` binds their channels to the head's channel vector and compiles clips to arrays, so the control
core receives nothing it has to parse. ``hello`` and ``clock`` (:data:`LocalRequest`) are answered by the server
itself.
"""

from __future__ import annotations

import numpy as np

from models import errors as E
from runtime import messages as M
from runtime.core import commands as C
from runtime.core.channels import ChannelMap, UnknownChannel
from runtime.core.clips import bind_clip

#: Requests the API server answers itself, never handed to the core.
LocalRequest = M.HelloRequest | M.ClockRequest


def check_channels(channels: ChannelMap, names: list[str] | tuple[str, ...]) -> np.ndarray:
    """Channel-vector indices of ``names``; ``unknown_channel`` naming the first the head does not know."""
    try:
        return channels.indices(names)
    except UnknownChannel as exc:
        raise E.UnknownChannel(f"unknown channel {str(exc.args[0])[:128]!r}; known: "
                               f"{', '.join(channels.names)}") from None


def to_command(req: M.Request, token: int, channels: ChannelMap, safe_speed: float,
               received: float | None = None) -> C.Command:
    """The core command for a decoded request (not a local op); ``received``: when it reached the daemon."""
    match req:
        case M.EnableRequest():
            return C.Enable(token)
        case M.DisableRequest():
            return C.Disable(token)
        case M.ResetRequest():
            return C.Reset(token)
        case M.StatusRequest():
            return C.Status(token)
        case M.PauseRequest():
            return C.Pause(token)
        case M.ResumeRequest():
            return C.Resume(token)
        case M.StopMotionRequest():
            return C.StopMotion(token)
        case M.EStopRequest():
            return C.EStop(token, req.reason or "api")
        case M.LoadClipRequest():
            return _load_clip(req.clip, token, channels)
        case M.UnloadClipRequest():
            return C.UnloadClip(token, req.clip)
        case M.PlayRequest():
            return C.Play(token, req.clip, req.at, float(req.from_ or 0.0), float(req.speed or 1.0), bool(req.loop))
        case M.SeekRequest():
            return C.Seek(token, req.time)
        case M.StreamRequest():
            idx = check_channels(channels, req.channels)
            arr = req.array()
            return C.Stream(token, np.ascontiguousarray(arr[:, 0]), idx, np.ascontiguousarray(arr[:, 1:]), received)
        case M.PoseRequest():
            names = list(req.pose)
            idx = check_channels(channels, names)
            speed = safe_speed if req.speed is None else req.speed
            return C.Pose(token, idx, np.array([req.pose[n] for n in names], dtype=float), speed)
        case M.RecordRequest():
            return C.Record(token, req.action, req.name or "recording")
        case M.HelloRequest() | M.ClockRequest():
            pass
    raise E.UnknownOp(f"op {type(req).__name__} is not served by the core")


def _load_clip(spec: M.ClipSpec, token: int, channels: ChannelMap) -> C.LoadClip:
    check_channels(channels, tuple(spec.channels))
    bound = bind_clip(spec, channels)
    return C.LoadClip(token, bound, bound.key_count, bound.nbytes)
