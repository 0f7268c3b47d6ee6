"""Reading a request's msgpack bytes without the schema: ids and ops of requests that fail to decode, float arrays
straight from the bytes, and msgspec's validation errors rewritten in the protocol's words.

:mod:`runtime.messages` holds the schema (one msgspec ``Struct`` per op) and decodes with it; what it cannot express
in the schema, and what it needs when a decode fails, lives here: the id to echo (:func:`lenient_id`,
:func:`request_id_of`, found by walking msgpack headers iteratively, so a deeply nested value never recurses), the
arrays of stream frames and clip keys (:func:`float_rows`: rows of float64 values read by numpy, no Python float per
value), and :func:`translate` (a msgspec ``ValidationError`` → the code and message of ``docs/protocol.md``, naming
the field path). The schema's shape reaches the rewriting as a :class:`SchemaInfo`, so this module imports no schema.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta, Struct

from models import errors as E
from models.protocol import error_for

MAX_NAME = 128  # clip, channel and string-id length
INTERPS = ("step", "linear", "bezier")
#: A request's id: an int, or a string of up to ``MAX_NAME`` characters (absent, or not a valid one: None).
RequestId = int | Annotated[str, Meta(max_length=MAX_NAME)]


@dataclass(frozen=True)
class SchemaInfo:
    """What the error rewriting needs to know of the schema: the request Struct of each op, the Struct of each nested
    map by its field path (``maps``: that path exactly; ``map_families``: any path under it, as one channel of a
    clip under ``clip.channels``), and the choices of enum fields by name (any other enum is an interpolation)."""

    ops: Mapping[str, type[Struct]]
    maps: Mapping[str, type[Struct]]
    map_families: Mapping[str, type[Struct]]
    enums: Mapping[str, tuple[str, ...]]

    def part(self, where: str) -> type[Struct] | None:
        """The Struct of the nested map at field path ``where``, if the schema has one there."""
        if where in self.maps:
            return self.maps[where]
        return next((s for prefix, s in self.map_families.items() if where.startswith(prefix)), None)


_NO_ID = object()


class _Envelope(Struct):
    """What can be read of any map request when the full decode fails: its id and op."""

    id: object = _NO_ID
    op: object = None


_envelope_decoder = msgspec.msgpack.Decoder(_Envelope)


def _valid_id(rid: object) -> RequestId | None:
    """``rid`` when it is a valid request id (an int, or a string of up to 128 chars), else None."""
    if (isinstance(rid, int) and not isinstance(rid, bool)) or (isinstance(rid, str) and len(rid) <= MAX_NAME):
        return rid
    return None


def lenient_id(raw: bytes) -> RequestId | None:
    """The request's id when it is a valid one (an int, or a string of up to 128 chars), else None."""
    try:
        rid = _envelope_decoder.decode(raw).id
    except (msgspec.MsgspecError, UnicodeDecodeError):
        return None
    except RecursionError:  # a deeply nested value elsewhere: find "id" among the top-level entries by hand
        rid = _scan_id(raw)
    return _valid_id(rid)


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


def request_id_of(raw: bytes, budget: int = 2000) -> RequestId | None:
    """The id of a request too large to decode, read from its top-level keys within ``budget`` steps (else None)."""
    return _valid_id(_scan_id(raw, budget))


def _scan_id(raw: bytes, budget: int = 100_000) -> object:
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
    return env.id is not _NO_ID and lenient_id(raw) is None


def _lenient_op(raw: bytes) -> str | None:
    try:
        op = _envelope_decoder.decode(raw).op
    except (msgspec.MsgspecError, RecursionError, UnicodeDecodeError):
        return None
    return op if isinstance(op, str) else None


_AT = re.compile(r"^(?P<what>.*?)(?: - at `(?P<path>[^`]*)`(?: in `(?P<where>[^`]*)`)?)?$", re.S)


def translate(text: str, raw: bytes, schema: SchemaInfo) -> tuple[str, str]:
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
        return "unknown_op", f"unknown op {op[:40]!r}; known: {', '.join(sorted(schema.ops))}"
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
        return ("bad_value" if in_clip else "bad_request"), _unknown_field(mm[1][:64], name, raw, schema)
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
        choices = ", ".join(schema.enums.get(name, INTERPS))
        return "bad_value", f"field {name!r} must be one of {choices} (got {mm[1][:40]})"
    if mm := re.match(r"Expected `([^`]*)`, got `([^`]*)`", what):
        expected = {"float": "a number", "str": "a string", "bool": "true or false", "object": "a map",
                    "array": "an array"}.get(mm[1].removesuffix(" | null"), mm[1])
        label = f"keys of field {name!r}" if key_of else f"field {name!r}"
        # A mistyped number inside frames, clips or pose values is a bad value (as the protocol has always said).
        value_like = in_clip or (mm[1].startswith("float") and re.match(r"^(frames\[\d+\]\[\d+\]|pose\b)", name))
        return ("bad_value" if value_like else "bad_request"), f"{label} must be {expected} (got {mm[2]})"
    return ("bad_value" if in_clip else "bad_request"), f"field {name!r}: {what.replace('`', '')}"


def _unknown_field(key: str, where: str, raw: bytes, schema: SchemaInfo) -> str:
    allowed = schema.part(where) if where else schema.ops.get(_lenient_op(raw) or "")
    names = sorted(f.encode_name for f in msgspec.structs.fields(allowed) if f.encode_name != "id") if allowed else []
    place = f"in {where!r}" if where else f"for op {_lenient_op(raw)!r}"
    return f"unknown field {key!r} {place}; allowed: {', '.join(names) or 'none'}"


class _ChannelShape(Struct, forbid_unknown_fields=True):
    """A channel map's shape, to find which channel of a clip msgspec's error was about."""

    keys: object
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


def finite(value: float, where: str) -> None:
    if not np.isfinite(value):
        raise E.BadValue(f"{where} must be finite (got {value!r})")


def all_finite(arr: np.ndarray, where: str) -> None:
    """BadValue naming the first NaN or infinity of a 2-D array as ``where[row][col]``."""
    if arr.size and not np.isfinite(arr).all():
        j, k = map(int, np.argwhere(~np.isfinite(arr))[0])
        raise E.BadValue(f"{where}[{j}][{k}] must be finite (got {float(arr[j, k])!r})")


_ROWS = msgspec.msgpack.Decoder(list[list[float]])
_ROW_PATH = re.compile(r"^\$(?:\[(\d+)\])?(?:\[(\d+)\])?$")


def array_header(raw: msgspec.Raw | bytes) -> tuple[int, int]:
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


def float_rows(raw: msgspec.Raw, width: int, max_rows: int, where: str, row_hint: str, container_code: str
                ) -> np.ndarray:
    """A msgpack array of ``width``-number arrays as a read-only (rows, width) float64 array.

    Rows of float64 values (what most packers write for floats) are read straight from the bytes with numpy; any
    other encoding (integers, float32, wrong widths, wrong types) is decoded by msgspec and checked row by row.
    Problems with the arrays themselves answer ``container_code``; a value that is not a number, ``bad_value``.
    """
    rows, head = array_header(raw)
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


def too_deep(value: object, limit: int) -> bool:
    """Whether lists and maps in ``value`` nest more than ``limit`` levels (iterative: no recursion)."""
    stack: list[tuple[Iterable[object], int]] = []
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


