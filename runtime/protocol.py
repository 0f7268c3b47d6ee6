"""The wire protocol (see ``docs/protocol.md``): msgpack maps over ZeroMQ, version, error codes, replies.

Requests are decoded and validated by the typed schemas of :mod:`runtime.messages`.

Requests are ``{"op": str, "id": int | str, ...}``; replies are ``{"id": same, "ok": true, ...}`` or
``{"id": same, "ok": false, "error": {"code": str, "message": str}}``. Telemetry is published as two frames,
topic (``b"state"`` or ``b"event"``) and a msgpack map.
"""

from __future__ import annotations

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


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def error_reply(rid: Any, code: str, message: str) -> dict[str, Any]:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message[:1000]}}
