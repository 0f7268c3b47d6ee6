"""Typed protocol requests: one msgspec ``Struct`` per op, decoded from msgpack and validated in one pass.

Each request is named after the core command it becomes (``EStopRequest`` → :class:`runtime.core.commands.EStop`,
``StopMotionRequest`` → ``StopMotion``; ``HelloRequest`` and ``ClockRequest`` the server answers itself).
:func:`decode_request` turns the bytes of one request into a :class:`Request` (a tagged union on ``op``) or raises
:class:`RequestError` (a :class:`~models.protocol.ProtocolError`) with the codes of ``docs/protocol.md`` and the
request id to echo. msgspec checks types, required and unknown fields, ranges and lengths while it decodes; what it
cannot express (finite numbers, frame widths, key order, duplicate channels) is checked in ``__post_init__`` with
numpy over whole arrays. The bulk of big requests, stream frames and clip keys, is kept by msgspec as raw msgpack
and read into float64 arrays by numpy (:func:`runtime.wire_scan.float_rows`), so no Python float is made for them;
a failed decode's message is rewritten in the protocol's words by :func:`runtime.wire_scan.translate`. Checks that
need the daemon's state (``play.at`` against its clock, channel names against the head, clip count) are left to the
caller.
"""

from __future__ import annotations

import re
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta, Struct, field

from models import errors as E
from models.protocol import ProtocolError, code_of
from runtime.wire_scan import (
    MAX_NAME,
    RequestId,
    SchemaInfo,
    all_finite,
    array_header,
    finite,
    float_rows,
    lenient_id,
    too_deep,
    translate,
)

MAX_CHANNELS = 256  # per clip, per stream request, per pose
MAX_CLIP_KEYS = 200_000  # per clip, all channels together
MAX_STREAM_FRAMES = 10_000  # per stream request
MAX_DEPTH = 32  # nesting of msgpack containers in one request
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")

Name = Annotated[str, Meta(min_length=1, max_length=MAX_NAME)]


class RequestError(ProtocolError):
    """A request that cannot be served as sent; ``request_id`` is the id to echo in the error reply (or None)."""

    def __init__(self, code: str, message: str, request_id: RequestId | None = None) -> None:
        super().__init__(code, message)
        self.request_id = request_id


class _Request(Struct, forbid_unknown_fields=True, tag_field="op", kw_only=True, dict=True):
    """Fields every request has; ``dict=True`` lets validation keep derived arrays next to the fields."""

    id: RequestId = None  # type: ignore[assignment]  # absent: None; an explicit null is refused


class HelloRequest(_Request, tag="hello"):
    client: object = None  # documented as a string; any value has always been accepted (and ignored)

    def __post_init__(self) -> None:
        if self.client is not None and too_deep(self.client, MAX_DEPTH - 1):
            raise E.BadRequest(f"field 'client': nested deeper than {MAX_DEPTH} levels")


class StatusRequest(_Request, tag="status"):
    pass


class EnableRequest(_Request, tag="enable"):
    pass


class DisableRequest(_Request, tag="disable"):
    pass


class EStopRequest(_Request, tag="estop"):
    reason: Annotated[str, Meta(min_length=1, max_length=200)] | None = None

    def __post_init__(self) -> None:
        if self.reason is None:
            self.reason = "api"


class ResetRequest(_Request, tag="reset"):
    pass


class ClockRequest(_Request, tag="clock"):
    t_client: float | None = None

    def __post_init__(self) -> None:
        if self.t_client is not None:
            finite(self.t_client, "field 't_client'")


class ChannelSpec(Struct, forbid_unknown_fields=True):
    """One channel of a clip: keys ``[t, value]`` (step, linear) or ``[t, value, in_dt, in_dv, out_dt, out_dv]``."""

    keys: msgspec.Raw  # parsed straight into an array by ClipSpec (see runtime.wire_scan.float_rows)
    interp: Literal["step", "linear", "bezier"] = "linear"


class ClipSpec(Struct, forbid_unknown_fields=True, dict=True):
    """A clip as the protocol carries it, validated; :meth:`key_array` gives a channel's keys as one array."""

    name: Name
    channels: Annotated[dict[Name, ChannelSpec], Meta(min_length=1, max_length=MAX_CHANNELS)]
    meta: object = None

    def __post_init__(self) -> None:
        total = sum(array_header(c.keys)[0] for c in self.channels.values())
        if total > MAX_CLIP_KEYS:
            raise E.TooLarge(f"clip {self.name!r} has {total} keys; at most {MAX_CLIP_KEYS}")
        if self.meta is not None and too_deep(self.meta, MAX_DEPTH - 2):
            raise E.BadRequest(f"clip {self.name!r}.meta: nested deeper than {MAX_DEPTH} levels")
        self._arrays = {ch: _check_keys(spec, f"clip {self.name!r}.channels.{ch}")
                        for ch, spec in self.channels.items()}

    def key_array(self, channel: str) -> np.ndarray:
        """Channel's keys as a float64 array of shape (keys, 2) or (keys, 6) (Bezier); validated, read-only."""
        arrays = self.__dict__.get("_arrays")
        if arrays is None:  # an instance built by hand rather than decoded
            arrays = self._arrays = {ch: _check_keys(spec, f"clip {self.name!r}.channels.{ch}")
                                     for ch, spec in self.channels.items()}
        return arrays[channel]

    @property
    def duration(self) -> float:
        """Last key time over all channels (as :attr:`models.clip.Clip.duration`)."""
        return max(float(self.key_array(ch)[-1, 0]) for ch in self.channels)

    def key_count(self) -> int:
        return sum(len(self.key_array(ch)) for ch in self.channels)

    def to_clip(self):  # -> models.clip.Clip (imported lazily: curves does not need messages)
        """The :class:`models.clip.Clip` of this spec (per-key Python objects: for files and tests, not cycles)."""
        from models.clip import Clip, make_curve

        return Clip(self.name, {ch: make_curve(spec.interp, self.key_array(ch).tolist(), f"clip {self.name!r}.{ch}")
                                for ch, spec in self.channels.items()})


class LoadClipRequest(_Request, tag="load_clip"):
    clip: ClipSpec


class UnloadClipRequest(_Request, tag="unload_clip"):
    clip: Name


class PlayRequest(_Request, tag="play"):
    """``at`` is a daemon-clock time (checked against the clock by the core); None values take the defaults."""

    clip: Name
    at: float | None = None
    from_: Annotated[float, Meta(ge=-3600, le=86400)] | None = field(default=None, name="from")
    speed: Annotated[float, Meta(ge=0.01, le=10.0)] | None = None
    loop: bool | None = None

    def __post_init__(self) -> None:
        if self.at is not None:
            finite(self.at, "field 'at'")
        if self.from_ is None:
            self.from_ = 0.0
        if self.speed is None:
            self.speed = 1.0
        if self.loop is None:
            self.loop = False


class PauseRequest(_Request, tag="pause"):
    pass


class ResumeRequest(_Request, tag="resume"):
    pass


class StopMotionRequest(_Request, tag="stop"):
    pass


class SeekRequest(_Request, tag="seek"):
    time: Annotated[float, Meta(ge=-3600, le=86400)]


class StreamRequest(_Request, tag="stream"):
    """Frames ``[t, v1 .. vN]`` for ``channels``; :meth:`array` holds them as one (frames, N + 1) float64 array."""

    channels: Annotated[list[Name], Meta(min_length=1, max_length=MAX_CHANNELS)]
    frames: msgspec.Raw  # parsed straight into an array (see runtime.wire_scan.float_rows)

    def __post_init__(self) -> None:
        if len(set(self.channels)) != len(self.channels):
            raise E.BadRequest("field 'channels' lists a channel twice")
        width = len(self.channels) + 1
        arr = float_rows(self.frames, width, MAX_STREAM_FRAMES, "frames", f"[t, {width - 1} values]", "bad_request")
        all_finite(arr, "frames")
        self._array = arr

    def array(self) -> np.ndarray:
        """The frames as a read-only float64 array: column 0 the times, then one column per channel."""
        arr = self.__dict__.get("_array")
        if arr is None:
            self.__post_init__()
            arr = self._array
        return arr


class PoseRequest(_Request, tag="pose"):
    pose: Annotated[dict[str, float], Meta(min_length=1, max_length=MAX_CHANNELS)]
    speed: Annotated[float, Meta(ge=0.01, le=1.0)] | None = None  # None: the daemon's safe speed

    def __post_init__(self) -> None:
        for ch, v in self.pose.items():
            if not np.isfinite(v):
                raise E.BadValue(f"pose[{ch[:64]!r}] must be finite (got {v!r})")


class RecordRequest(_Request, tag="record"):
    action: Literal["start", "stop"]
    name: Annotated[str, Meta(min_length=1, max_length=64)] | None = None

    def __post_init__(self) -> None:
        if self.name is None:
            self.name = "recording"
        elif not _RECORD_NAME.match(self.name):
            raise E.BadValue("record name: letters, digits, _ . - only (max 64)")


Request = (HelloRequest | StatusRequest | EnableRequest | DisableRequest | EStopRequest | ResetRequest
           | ClockRequest | LoadClipRequest | UnloadClipRequest | PlayRequest | PauseRequest | ResumeRequest
           | StopMotionRequest | SeekRequest | StreamRequest | PoseRequest | RecordRequest)
OP_TYPES: dict[str, type[_Request]] = {c.__struct_config__.tag: c for c in Request.__args__}  # type: ignore[attr-defined]
OPS = tuple(sorted(OP_TYPES))

_decoder = msgspec.msgpack.Decoder(Request)
_SCHEMA = SchemaInfo(OP_TYPES, {"clip": ClipSpec}, {"clip.channels": ChannelSpec}, {"action": ("start", "stop")})


def decode_request(raw: bytes) -> Request:
    """Decode and validate one request; every problem is a :class:`RequestError` carrying the id to echo."""
    try:
        return _decoder.decode(raw)
    except RequestError:
        raise
    except E.LikenessError as exc:  # raised by a __post_init__ check
        raise RequestError(code_of(exc), exc.message, lenient_id(raw)) from None
    except msgspec.ValidationError as exc:
        code, message = translate(str(exc), raw, _SCHEMA)
        raise RequestError(code, message, lenient_id(raw)) from None
    except msgspec.DecodeError as exc:
        raise RequestError("bad_request", f"not a msgpack message: {exc}", None) from None
    except UnicodeDecodeError:
        raise RequestError("bad_request", "a string is not valid UTF-8", lenient_id(raw)) from None
    except RecursionError:
        raise RequestError("bad_request", f"a value is nested deeper than {MAX_DEPTH} levels",
                           lenient_id(raw)) from None


def _check_keys(spec: ChannelSpec, where: str) -> np.ndarray:
    """A channel's keys as one array after the checks of :func:`models.clip.make_curve` (same messages)."""
    width = 6 if spec.interp == "bezier" else 2
    arr = float_rows(spec.keys, width, MAX_CLIP_KEYS, f"{where}.keys", f"a list of {width} numbers for {spec.interp}",
                      "bad_value")
    if not len(arr):
        raise E.BadValue(f"{where}.keys: must be a non-empty list of keys")
    all_finite(arr, f"{where}.keys")
    if len(arr) > 1:
        bad = np.flatnonzero(np.diff(arr[:, 0]) <= 0)
        if bad.size:
            j = int(bad[0]) + 1
            raise E.BadValue(f"{where}.keys[{j}]: times must increase strictly "
                                f"({float(arr[j, 0])!r} after {float(arr[j - 1, 0])!r})")
    if width == 6:
        bad = np.flatnonzero((arr[:, 2] > 0) | (arr[:, 4] < 0))
        if bad.size:
            j = int(bad[0])
            raise E.BadValue(f"{where}.keys[{j}]: need in_dt <= 0 <= out_dt (got in_dt="
                                f"{float(arr[j, 2])!r}, out_dt={float(arr[j, 4])!r})")
    return arr


__all__ = [
    "MAX_CHANNELS",
    "MAX_CLIP_KEYS",
    "MAX_DEPTH",
    "MAX_STREAM_FRAMES",
    "OPS",
    "OP_TYPES",
    "ChannelSpec",
    "ClipSpec",
    "ClockRequest",
    "DisableRequest",
    "EStopRequest",
    "EnableRequest",
    "HelloRequest",
    "LoadClipRequest",
    "PauseRequest",
    "PlayRequest",
    "PoseRequest",
    "RecordRequest",
    "Request",
    "RequestError",
    "ResetRequest",
    "ResumeRequest",
    "SeekRequest",
    "StatusRequest",
    "StopMotionRequest",
    "StreamRequest",
    "UnloadClipRequest",
    "decode_request",
]
