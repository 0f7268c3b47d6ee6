"""The wire protocol (see ``docs/protocol.md``): msgpack maps over ZeroMQ, version, error codes, field checks.

Requests are ``{"op": str, "id": int | str, ...}``; replies are ``{"id": same, "ok": true, ...}`` or
``{"id": same, "ok": false, "error": {"code": str, "message": str}}``. Telemetry is published as two frames,
topic (``b"state"`` or ``b"event"``) and a msgpack map.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import msgpack

PROTOCOL_VERSION = 1
TOPIC_STATE = b"state"
TOPIC_EVENT = b"event"

#: Error codes a reply may carry.
ERROR_CODES = (
    "bad_request",  # not a map, missing/mistyped fields, unknown fields
    "unknown_op",
    "bad_value",  # a value out of range, non-finite, malformed clip
    "unknown_channel",
    "not_found",  # clip or recording not known
    "bad_state",  # operation not allowed in the current lifecycle state
    "estop",  # latched e-stop: only status/hello/clock/reset
    "fault",  # the head is in FAULT: reset first
    "too_large",
    "hardware",  # a bus refused or failed during a lifecycle transition
    "internal",
)


class ProtocolError(Exception):
    """Turned into an error reply ``{"code": code, "message": message}``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def unpack(raw: bytes) -> Any:
    """Decode one request; malformed msgpack → ProtocolError(bad_request)."""
    try:
        return msgpack.unpackb(raw, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:
        raise ProtocolError("bad_request", f"not a msgpack message: {type(exc).__name__}") from None


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def request_id(msg: Any) -> Any:
    """The id to echo: an int, or a string of up to 128 characters; anything else echoes as None."""
    if isinstance(msg, Mapping):
        rid = msg.get("id")
        if (isinstance(rid, int) and not isinstance(rid, bool) and -(2**63) <= rid < 2**64) or (
            isinstance(rid, str) and len(rid) <= 128
        ):
            return rid
    return None


def error_reply(rid: Any, code: str, message: str) -> dict[str, Any]:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message[:1000]}}


class Fields:
    """Typed access to a request's fields; every problem is a ProtocolError naming the field."""

    def __init__(self, msg: Mapping[str, Any], allowed: set[str]) -> None:
        extra = [k for k in msg if k not in allowed and k not in ("op", "id")]
        if extra:
            raise ProtocolError("bad_request", f"unknown field(s) {sorted(map(str, extra))[:8]} for op "
                                f"{msg.get('op')!r}; allowed: {', '.join(sorted(allowed)) or 'none'}")
        self.msg = msg

    def has(self, key: str) -> bool:
        return key in self.msg and self.msg[key] is not None

    def number(self, key: str, default: Any = ..., lo: float | None = None, hi: float | None = None,
               positive: bool = False) -> float:
        value = self.msg.get(key)
        if value is None:
            if default is ...:
                raise ProtocolError("bad_request", f"field {key!r} is required")
            return default
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProtocolError("bad_request", f"field {key!r} must be a number (got {type(value).__name__})")
        value = float(value)
        if not math.isfinite(value):
            raise ProtocolError("bad_value", f"field {key!r} must be finite (got {value!r})")
        if positive and value <= 0:
            raise ProtocolError("bad_value", f"field {key!r} must be positive (got {value!r})")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ProtocolError("bad_value", f"field {key!r} must lie in [{lo}, {hi}] (got {value!r})")
        return value

    def boolean(self, key: str, default: bool = False) -> bool:
        value = self.msg.get(key, default)
        if value is None:
            return default
        if not isinstance(value, bool):
            raise ProtocolError("bad_request", f"field {key!r} must be true or false (got {type(value).__name__})")
        return value

    def string(self, key: str, default: Any = ..., max_len: int = 128) -> str:
        value = self.msg.get(key)
        if value is None:
            if default is ...:
                raise ProtocolError("bad_request", f"field {key!r} is required")
            return default
        if not isinstance(value, str) or not value or len(value) > max_len:
            raise ProtocolError("bad_request", f"field {key!r} must be a string of 1..{max_len} characters")
        return value

    def mapping(self, key: str) -> Mapping[str, Any]:
        value = self.msg.get(key)
        if not isinstance(value, Mapping):
            raise ProtocolError("bad_request", f"field {key!r} must be a map")
        return value

    def array(self, key: str, max_len: int) -> list[Any]:
        value = self.msg.get(key)
        if not isinstance(value, list):
            raise ProtocolError("bad_request", f"field {key!r} must be an array")
        if len(value) > max_len:
            raise ProtocolError("too_large", f"field {key!r} has {len(value)} items; at most {max_len}")
        return value


def finite_number(value: Any, where: str) -> float:
    """A finite float or ProtocolError(bad_value) naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolError("bad_value", f"{where} must be a number (got {type(value).__name__})")
    value = float(value)
    if not math.isfinite(value):
        raise ProtocolError("bad_value", f"{where} must be finite (got {value!r})")
    return value
