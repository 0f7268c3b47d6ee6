"""Typed protocol requests: one msgspec ``Struct`` per op, decoded from msgpack and validated in one pass.

:func:`decode_request` turns the bytes of one request into a :class:`Request` (a tagged union on ``op``) or raises
:class:`RequestError` (a :class:`~models.protocol.ProtocolError`) with the codes of ``docs/protocol.md`` and the
request id to echo. msgspec checks types, required and unknown fields, ranges and lengths while it decodes; what it
cannot express (finite numbers, frame widths, key order, duplicate channels) is checked in ``__post_init__`` with
numpy over whole arrays. The bulk of big requests, stream frames and clip keys, is kept by msgspec as raw msgpack
and read into float64 arrays by numpy (rows of float64 values straight from the bytes, anything else through a
typed msgspec decode), so no Python float is made for them. Checks that need the daemon's state (``play.at``
against its clock, channel names against the head, clip count) are left to the caller.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterable
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
from msgspec import Meta, Struct, field

from models import errors as E
from models.protocol import ProtocolError, code_of, error_for

MAX_NAME = 128  # clip, channel and string-id length
MAX_CHANNELS = 256  # per clip, per stream request, per pose
MAX_CLIP_KEYS = 200_000  # per clip, all channels together
MAX_STREAM_FRAMES = 10_000  # per stream request
MAX_DEPTH = 32  # nesting of msgpack containers in one request
INTERPS = ("step", "linear", "bezier")
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")

Name = Annotated[str, Meta(min_length=1, max_length=MAX_NAME)]
RequestId = int | Annotated[str, Meta(max_length=MAX_NAME)]


class RequestError(ProtocolError):
    """A request that cannot be served as sent; ``request_id`` is the id to echo in the error reply (or None)."""

    def __init__(self, code: str, message: str, request_id: Any = None) -> None:
        super().__init__(code, message)
        self.request_id = request_id


class _Request(Struct, forbid_unknown_fields=True, tag_field="op", kw_only=True, dict=True):
    """Fields every request has; ``dict=True`` lets validation keep derived arrays next to the fields."""

    id: RequestId = None  # type: ignore[assignment]  # absent: None; an explicit null is refused


class Hello(_Request, tag="hello"):
    client: Any = None  # documented as a string; any value has always been accepted (and ignored)

    def __post_init__(self) -> None:
        if self.client is not None and _too_deep(self.client, MAX_DEPTH - 1):
            raise E.BadRequest(f"field 'client': nested deeper than {MAX_DEPTH} levels")


class Status(_Request, tag="status"):
    pass


class Enable(_Request, tag="enable"):
    pass


class Disable(_Request, tag="disable"):
    pass


class Estop(_Request, tag="estop"):
    reason: Annotated[str, Meta(min_length=1, max_length=200)] | None = None

    def __post_init__(self) -> None:
        if self.reason is None:
            self.reason = "api"


class Reset(_Request, tag="reset"):
    pass


class Clock(_Request, tag="clock"):
    t_client: float | None = None

    def __post_init__(self) -> None:
        if self.t_client is not None:
            _finite(self.t_client, "field 't_client'")


class ChannelSpec(Struct, forbid_unknown_fields=True):
    """One channel of a clip: keys ``[t, value]`` (step, linear) or ``[t, value, in_dt, in_dv, out_dt, out_dv]``."""

    keys: msgspec.Raw  # parsed straight into an array by ClipSpec (see _float_rows)
    interp: Literal["step", "linear", "bezier"] = "linear"


class ClipSpec(Struct, forbid_unknown_fields=True, dict=True):
    """A clip as the protocol carries it, validated; :meth:`key_array` gives a channel's keys as one array."""

    name: Name
    channels: Annotated[dict[Name, ChannelSpec], Meta(min_length=1, max_length=MAX_CHANNELS)]
    meta: Any = None

    def __post_init__(self) -> None:
        total = sum(_array_header(c.keys)[0] for c in self.channels.values())
        if total > MAX_CLIP_KEYS:
            raise E.TooLarge(f"clip {self.name!r} has {total} keys; at most {MAX_CLIP_KEYS}")
        if self.meta is not None and _too_deep(self.meta, MAX_DEPTH - 2):
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


class LoadClip(_Request, tag="load_clip"):
    clip: ClipSpec


class UnloadClip(_Request, tag="unload_clip"):
    clip: Name


class Play(_Request, tag="play"):
    """``at`` is a daemon-clock time (checked against the clock by the core); None values take the defaults."""

    clip: Name
    at: float | None = None
    from_: Annotated[float, Meta(ge=-3600, le=86400)] | None = field(default=None, name="from")
    speed: Annotated[float, Meta(ge=0.01, le=10.0)] | None = None
    loop: bool | None = None

    def __post_init__(self) -> None:
        if self.at is not None:
            _finite(self.at, "field 'at'")
        if self.from_ is None:
            self.from_ = 0.0
        if self.speed is None:
            self.speed = 1.0
        if self.loop is None:
            self.loop = False


class Pause(_Request, tag="pause"):
    pass


class Resume(_Request, tag="resume"):
    pass


class Stop(_Request, tag="stop"):
    pass


class Seek(_Request, tag="seek"):
    time: Annotated[float, Meta(ge=-3600, le=86400)]


class Stream(_Request, tag="stream"):
    """Frames ``[t, v1 .. vN]`` for ``channels``; :meth:`array` holds them as one (frames, N + 1) float64 array."""

    channels: Annotated[list[Name], Meta(min_length=1, max_length=MAX_CHANNELS)]
    frames: msgspec.Raw  # parsed straight into an array (see _float_rows)

    def __post_init__(self) -> None:
        if len(set(self.channels)) != len(self.channels):
            raise E.BadRequest("field 'channels' lists a channel twice")
        width = len(self.channels) + 1
        arr = _float_rows(self.frames, width, MAX_STREAM_FRAMES, "frames", f"[t, {width - 1} values]", "bad_request")
        _all_finite(arr, "frames")
        self._array = arr

    def array(self) -> np.ndarray:
        """The frames as a read-only float64 array: column 0 the times, then one column per channel."""
        arr = self.__dict__.get("_array")
        if arr is None:
            self.__post_init__()
            arr = self._array
        return arr


class Pose(_Request, tag="pose"):
    pose: Annotated[dict[str, float], Meta(min_length=1, max_length=MAX_CHANNELS)]
    speed: Annotated[float, Meta(ge=0.01, le=1.0)] | None = None  # None: the daemon's safe speed

    def __post_init__(self) -> None:
        for ch, v in self.pose.items():
            if not np.isfinite(v):
                raise E.BadValue(f"pose[{ch[:64]!r}] must be finite (got {v!r})")


class Record(_Request, tag="record"):
    action: Literal["start", "stop"]
    name: Annotated[str, Meta(min_length=1, max_length=64)] | None = None

    def __post_init__(self) -> None:
        if self.name is None:
            self.name = "recording"
        elif not _RECORD_NAME.match(self.name):
            raise E.BadValue("record name: letters, digits, _ . - only (max 64)")


Request = (Hello | Status | Enable | Disable | Estop | Reset | Clock | LoadClip | UnloadClip | Play | Pause | Resume
           | Stop | Seek | Stream | Pose | Record)
OP_TYPES: dict[str, type[_Request]] = {c.__struct_config__.tag: c for c in Request.__args__}  # type: ignore[attr-defined]
OPS = tuple(sorted(OP_TYPES))

_decoder = msgspec.msgpack.Decoder(Request)


_NO_ID = object()


class _Envelope(Struct):
    """What can be read of any map request when the full decode fails: its id and op."""

    id: Any = _NO_ID
    op: Any = None


_envelope_decoder = msgspec.msgpack.Decoder(_Envelope)


def decode_request(raw: bytes) -> Request:
    """Decode and validate one request; every problem is a :class:`RequestError` carrying the id to echo."""
    try:
        return _decoder.decode(raw)
    except RequestError:
        raise
    except E.LikenessError as exc:  # raised by a __post_init__ check
        raise RequestError(code_of(exc), exc.message, _lenient_id(raw)) from None
    except msgspec.ValidationError as exc:
        code, message = _translate(str(exc), raw)
        raise RequestError(code, message, _lenient_id(raw)) from None
    except msgspec.DecodeError as exc:
        raise RequestError("bad_request", f"not a msgpack message: {exc}", None) from None
    except UnicodeDecodeError:
        raise RequestError("bad_request", "a string is not valid UTF-8", _lenient_id(raw)) from None
    except RecursionError:
        raise RequestError("bad_request", f"a value is nested deeper than {MAX_DEPTH} levels",
                           _lenient_id(raw)) from None


def _lenient_id(raw: bytes) -> Any:
    """The request's id when it is a valid one (an int, or a string of up to 128 chars), else None."""
    try:
        rid = _envelope_decoder.decode(raw).id
    except (msgspec.MsgspecError, UnicodeDecodeError):
        return None
    except RecursionError:  # a deeply nested value elsewhere: find "id" among the top-level entries by hand
        rid = _scan_id(raw)
    if (isinstance(rid, int) and not isinstance(rid, bool)) or (isinstance(rid, str) and len(rid) <= MAX_NAME):
        return rid
    return None


def _msgpack_heads() -> dict[int, tuple[int, int, str]]:
    """msgpack first byte → (bytes of its length field, payload bytes or -1 if given by that field, kind)."""
    heads: dict[int, tuple[int, int, str]] = {}
    for b in range(0x00, 0x80):
        heads[b] = (0, 0, "")  # positive fixint
    for b in range(0xE0, 0x100):
        heads[b] = (0, 0, "")  # negative fixint
    for b in range(0x80, 0x90):
        heads[b] = (0, b & 0x0F, "map")
    for b in range(0x90, 0xA0):
        heads[b] = (0, b & 0x0F, "array")
    for b in range(0xA0, 0xC0):
        heads[b] = (0, b & 0x1F, "")  # fixstr
    heads.update({0xC0: (0, 0, ""), 0xC2: (0, 0, ""), 0xC3: (0, 0, ""),
                  0xC4: (1, -1, ""), 0xC5: (2, -1, ""), 0xC6: (4, -1, ""),  # bin: length field, then bytes
                  0xC7: (1, -1, "ext"), 0xC8: (2, -1, "ext"), 0xC9: (4, -1, "ext"),  # length, type, bytes
                  0xCA: (0, 4, ""), 0xCB: (0, 8, ""), 0xCC: (0, 1, ""), 0xCD: (0, 2, ""), 0xCE: (0, 4, ""),
                  0xCF: (0, 8, ""), 0xD0: (0, 1, ""), 0xD1: (0, 2, ""), 0xD2: (0, 4, ""), 0xD3: (0, 8, ""),
                  0xD4: (0, 2, ""), 0xD5: (0, 3, ""), 0xD6: (0, 5, ""), 0xD7: (0, 9, ""), 0xD8: (0, 17, ""),
                  0xD9: (1, -1, ""), 0xDA: (2, -1, ""), 0xDB: (4, -1, ""),  # str8/16/32
                  0xDC: (2, -1, "array"), 0xDD: (4, -1, "array"), 0xDE: (2, -1, "map"), 0xDF: (4, -1, "map")})
    return heads


_HEADS = _msgpack_heads()


def _skip(raw: bytes, pos: int, budget: int) -> int:
    """Position after the msgpack value at ``pos``, walking nested containers with a counter, not recursion.

    Raises IndexError/KeyError on malformed data and ValueError after ``budget`` items.
    """
    pending = 1
    while pending:
        budget -= 1
        if budget < 0:
            raise ValueError("too many items")
        lenbytes, size, kind = _HEADS[raw[pos]]
        pos += 1
        if size < 0:  # a length field follows the type byte
            size = int.from_bytes(raw[pos:pos + lenbytes], "big")
            pos += lenbytes
        pending -= 1
        if kind == "array":
            pending += size
        elif kind == "map":
            pending += 2 * size
        else:
            pos += size + (kind == "ext")
            if pos > len(raw):
                raise IndexError("truncated")
    return pos


def request_id_of(raw: bytes, budget: int = 2000) -> Any:
    """The id of a request too large to decode, read from its top-level keys within ``budget`` steps (else None)."""
    rid = _scan_id(raw, budget)
    if (isinstance(rid, int) and not isinstance(rid, bool)) or (isinstance(rid, str) and len(rid) <= MAX_NAME):
        return rid
    return None


def _scan_id(raw: bytes, budget: int = 100_000) -> Any:
    """The top-level ``id`` of a msgpack map, read without decoding the other values (None if not found)."""
    try:
        lenbytes, size, kind = _HEADS[raw[0]]
        if kind != "map":
            return None
        pos = 1
        if size < 0:
            size, pos = int.from_bytes(raw[1:1 + lenbytes], "big"), 1 + lenbytes
        for _ in range(size):
            end = _skip(raw, pos, budget)
            key = raw[pos:end]
            if key == b"\xa2id":
                return msgspec.msgpack.decode(raw[end:_skip(raw, end, 64)])
            pos = _skip(raw, end, budget)
    except (IndexError, KeyError, ValueError, msgspec.MsgspecError, RecursionError):  # (UnicodeDecodeError too)
        pass
    return None


def _has_bad_id(raw: bytes) -> bool:
    """Whether the request map has an ``id`` that is not a valid one."""
    try:
        env = _envelope_decoder.decode(raw)
    except (msgspec.MsgspecError, RecursionError, UnicodeDecodeError):
        return False
    return env.id is not _NO_ID and _lenient_id(raw) is None


def _lenient_op(raw: bytes) -> str | None:
    try:
        op = _envelope_decoder.decode(raw).op
    except (msgspec.MsgspecError, RecursionError, UnicodeDecodeError):
        return None
    return op if isinstance(op, str) else None


_AT = re.compile(r"^(?P<what>.*?)(?: - at `(?P<path>[^`]*)`(?: in `(?P<where>[^`]*)`)?)?$", re.S)


def _translate(text: str, raw: bytes) -> tuple[str, str]:
    """(code, message) in the protocol's terms for a msgspec ValidationError message."""
    m = _AT.match(text)
    assert m is not None  # the pattern matches any text
    what, path, where = m["what"], m["path"] or "$", m["where"]
    key_of = where is not None  # "at `key` in `$.x`": the problem is a map key of $.x
    if key_of:
        path = where
    if "[...]" in path:
        path = _resolve_wildcards(path, raw)
    name = path[2:] if path.startswith("$.") else path[1:]
    # Inside a load_clip's clip map every problem is a bad value (a malformed clip), as the protocol has always said.
    in_clip = (name.startswith(("clip.", "clip[")) or (name == "clip" and what.startswith("Object "))) and (
        _lenient_op(raw) == "load_clip")

    if path == "$.op" and what.startswith("Invalid value"):
        if _has_bad_id(raw):  # a malformed id is reported first, as it always was
            return "bad_request", "field 'id' must be an integer or a string of up to 128 chars"
        op = _lenient_op(raw) or ""
        return "unknown_op", f"unknown op {op[:40]!r}; known: {', '.join(OPS)}"
    if path == "$.op" or (path == "$" and "field `op`" in what):
        return "bad_request", "field 'op' must be a string naming the operation"
    if path == "$" and what.startswith("Expected `object`"):
        return "bad_request", "a request must be a map with 'op' and 'id'"
    if path == "$.id":
        return "bad_request", "field 'id' must be an integer or a string of up to 128 chars"
    if mm := re.match(r"Object missing required field `(.*)`", what):
        full = f"{name}.{mm[1]}" if name else mm[1]
        return ("bad_value" if in_clip else "bad_request"), f"field {full!r} is required"
    if mm := re.match(r"Object contains unknown field `(.*)`", what):
        return ("bad_value" if in_clip else "bad_request"), _unknown_field(mm[1][:64], name, raw)
    if mm := re.match(r"Expected `(array|object)` of length <= (\d+)", what):
        return "too_large", f"field {name!r} has more than {mm[2]} items"
    if mm := re.match(r"Expected `(array|object)` of length >= (\d+)", what):
        return ("bad_value" if in_clip else "bad_request"), f"field {name!r} must have at least {mm[2]} item(s)"
    if mm := re.match(r"Expected `str` of length ([<>]=) (\d+)", what):
        bound = "at most" if mm[1] == "<=" else "at least"
        label = f"keys of field {name!r} must be strings" if key_of else f"field {name!r} must be a string"
        return ("bad_value" if in_clip else "bad_request"), f"{label} of {bound} {mm[2]} characters"
    if mm := re.match(r"Expected `(float|int)` ([<>]=?) (\S+)", what):
        return "bad_value", f"field {name!r} must be a finite number {mm[2]} {mm[3]}"
    if mm := re.match(r"Invalid enum value (.*)", what):
        choices = _choices(name)
        return "bad_value", f"field {name!r} must be one of {choices} (got {mm[1][:40]})"
    if mm := re.match(r"Expected `([^`]*)`, got `([^`]*)`", what):
        expected = {"float": "a number", "str": "a string", "bool": "true or false", "object": "a map",
                    "array": "an array"}.get(mm[1].removesuffix(" | null"), mm[1])
        label = f"keys of field {name!r}" if key_of else f"field {name!r}"
        # A mistyped number inside frames, clips or pose values is a bad value (as the protocol has always said).
        value_like = in_clip or (mm[1].startswith("float") and re.match(r"^(frames\[\d+\]\[\d+\]|pose\b)", name))
        return ("bad_value" if value_like else "bad_request"), f"{label} must be {expected} (got {mm[2]})"
    return ("bad_value" if in_clip else "bad_request"), f"field {name!r}: {what.replace('`', '')}"


def _unknown_field(key: str, where: str, raw: bytes) -> str:
    if where:
        allowed = {"clip": ClipSpec}.get(where, ChannelSpec if where.startswith("clip.channels") else None)
    else:
        allowed = OP_TYPES.get(_lenient_op(raw) or "")
    names = sorted(f.encode_name for f in msgspec.structs.fields(allowed) if f.encode_name != "id") if allowed else []
    place = f"in {where!r}" if where else f"for op {_lenient_op(raw)!r}"
    return f"unknown field {key!r} {place}; allowed: {', '.join(names) or 'none'}"


def _choices(name: str) -> str:
    if name == "action":
        return "start, stop"
    return ", ".join(INTERPS)


class _ChannelShape(Struct, forbid_unknown_fields=True):
    """A channel map's shape, to find which channel of a clip msgspec's error was about."""

    keys: Any
    interp: Literal["step", "linear", "bezier"] = "linear"


def _resolve_wildcards(path: str, raw: bytes) -> str:
    """Name the map key msgspec writes as ``[...]`` for clip channels and pose values (decodes again: error path)."""
    try:
        msg = msgspec.msgpack.decode(raw)
    except (msgspec.MsgspecError, RecursionError, UnicodeDecodeError):
        return path
    try:
        if path.startswith("$.clip.channels[...]"):
            for ch, spec in msg["clip"]["channels"].items():
                try:
                    msgspec.convert(spec, _ChannelShape)
                except msgspec.ValidationError:
                    return path.replace("[...]", f".{str(ch)[:MAX_NAME]}", 1)
        if path.startswith("$.pose[...]"):
            for ch, v in msg["pose"].items():
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    return f"$.pose[{str(ch)[:64]!r}]"
    except (KeyError, TypeError, AttributeError):
        pass
    return path


def _finite(value: float, where: str) -> None:
    if not np.isfinite(value):
        raise E.BadValue(f"{where} must be finite (got {value!r})")


def _all_finite(arr: np.ndarray, where: str) -> None:
    """BadValue naming the first NaN or infinity of a 2-D array as ``where[row][col]``."""
    if arr.size and not np.isfinite(arr).all():
        j, k = map(int, np.argwhere(~np.isfinite(arr))[0])
        raise E.BadValue(f"{where}[{j}][{k}] must be finite (got {float(arr[j, k])!r})")


def _check_keys(spec: ChannelSpec, where: str) -> np.ndarray:
    """A channel's keys as one array after the checks of :func:`models.clip.make_curve` (same messages)."""
    width = 6 if spec.interp == "bezier" else 2
    arr = _float_rows(spec.keys, width, MAX_CLIP_KEYS, f"{where}.keys", f"a list of {width} numbers for {spec.interp}",
                      "bad_value")
    if not len(arr):
        raise E.BadValue(f"{where}.keys: must be a non-empty list of keys")
    _all_finite(arr, f"{where}.keys")
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


_ROWS = msgspec.msgpack.Decoder(list[list[float]])
_ROW_PATH = re.compile(r"^\$(?:\[(\d+)\])?(?:\[(\d+)\])?$")


def _array_header(raw: msgspec.Raw | bytes) -> tuple[int, int]:
    """(items, header bytes) of a msgpack array; (0, 0) when it is not one."""
    buf = memoryview(raw)
    if not len(buf):
        return 0, 0
    head = buf[0]
    if 0x90 <= head <= 0x9F:
        return head & 0x0F, 1
    if head == 0xDC and len(buf) >= 3:
        return int.from_bytes(buf[1:3], "big"), 3
    if head == 0xDD and len(buf) >= 5:
        return int.from_bytes(buf[1:5], "big"), 5
    return 0, 0


def _float_rows(raw: msgspec.Raw, width: int, max_rows: int, where: str, row_hint: str, container_code: str
                ) -> np.ndarray:
    """A msgpack array of ``width``-number arrays as a read-only (rows, width) float64 array.

    Rows of float64 values (what most packers write for floats) are read straight from the bytes with numpy; any
    other encoding (integers, float32, wrong widths, wrong types) is decoded by msgspec and checked row by row.
    Problems with the arrays themselves answer ``container_code``; a value that is not a number, ``bad_value``.
    """
    rows, head = _array_header(raw)
    if rows > max_rows:
        raise E.TooLarge(f"field {where!r} has {rows} items; at most {max_rows}")
    arr = _float64_rows(memoryview(raw), rows, head, width) if head else None
    if arr is None:
        try:
            lists = _ROWS.decode(raw)
        except msgspec.ValidationError as exc:
            m = _AT.match(str(exc))
            assert m is not None
            pm = _ROW_PATH.match(m["path"] or "$")
            j, k = (pm[1], pm[2]) if pm else (None, None)
            if k is not None:
                got = re.search(r"got `([^`]*)`", m["what"])
                raise E.BadValue(f"{where}[{j}][{k}] must be a number (got {got[1] if got else '?'})"
                                    ) from None
            if j is not None:
                raise error_for(container_code, f"{where}[{j}] must be {row_hint}") from None
            raise error_for(container_code, f"field {where!r} must be an array of {row_hint}") from None
        if any(len(r) != width for r in lists):
            j = next(j for j, r in enumerate(lists) if len(r) != width)
            raise error_for(container_code, f"{where}[{j}] must be {row_hint} (got {len(lists[j])} numbers)")
        arr = np.fromiter(itertools.chain.from_iterable(lists), np.float64, len(lists) * width)
        arr = arr.reshape(len(lists), width)
    arr.flags.writeable = False
    return arr


def _float64_rows(buf: memoryview, rows: int, head: int, width: int) -> np.ndarray | None:
    """The rows when every one is ``width`` msgpack float64 values (0xCB + 8 bytes big-endian), else None."""
    row_head = bytes([0x90 | width]) if width < 16 else b"\xdc" + width.to_bytes(2, "big")
    size = len(row_head) + 9 * width
    if rows == 0 or len(buf) - head != rows * size:
        return None
    cells = np.frombuffer(buf, np.uint8, offset=head).reshape(rows, size)
    if not (cells[:, :len(row_head)] == np.frombuffer(row_head, np.uint8)).all():
        return None
    cells = cells[:, len(row_head):].reshape(rows, width, 9)
    if not (cells[:, :, 0] == 0xCB).all():
        return None
    return np.ascontiguousarray(cells[:, :, 1:]).view(">f8").reshape(rows, width).astype(np.float64)


def _too_deep(value: Any, limit: int) -> bool:
    """Whether lists and maps in ``value`` nest more than ``limit`` levels (iterative: no recursion)."""
    stack: list[tuple[Iterable[Any], int]] = []
    if isinstance(value, (list, dict)):
        stack.append((value.values() if isinstance(value, dict) else value, 1))
    while stack:
        items, depth = stack.pop()
        if depth > limit:
            return True
        for v in items:
            if isinstance(v, dict):
                stack.append((v.values(), depth + 1))
            elif isinstance(v, list):
                stack.append((v, depth + 1))
    return False


__all__ = [
    "MAX_CHANNELS", "MAX_CLIP_KEYS", "MAX_DEPTH", "MAX_STREAM_FRAMES", "OPS", "OP_TYPES", "ChannelSpec", "ClipSpec",
    "Clock", "Disable", "Enable", "Estop", "Hello", "LoadClip", "Pause", "Play", "Pose", "Record", "Request",
    "RequestError", "Reset", "Resume", "Seek", "Status", "Stop", "Stream", "UnloadClip", "decode_request",
]
