"""The wire protocol (see ``docs/protocol.md``): msgpack maps over ZeroMQ, version, error codes, replies.

Requests are decoded and validated by the typed schemas of :mod:`runtime.messages` (the daemon side).

Requests are ``{"op": str, "id": int | str, ...}``; replies are ``{"id": same, "ok": true, ...}`` or
``{"id": same, "ok": false, "error": {"code": str, "message": str}}``. Telemetry is published as two frames,
topic (``b"state"`` or ``b"event"``) and a msgpack map.
"""

from __future__ import annotations

from typing import Any

import msgpack

from models import errors as E

PROTOCOL_VERSION = 1
TOPIC_STATE = b"state"
TOPIC_EVENT = b"event"

#: Error codes a reply may carry (docs/protocol.md), one per kind of :mod:`models.errors` error.
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

#: The one table from typed errors to protocol codes; a subclass not listed takes its nearest listed base's code.
ERROR_CODE_OF: dict[type[E.LikenessError], str] = {
    E.BadRequest: "bad_request",
    E.UnknownOp: "unknown_op",
    E.BadValue: "bad_value",
    E.UnknownChannel: "unknown_channel",
    E.NotFound: "not_found",
    E.BadState: "bad_state",
    E.EStopLatched: "estop",
    E.Faulted: "fault",
    E.TooLarge: "too_large",
    E.HardwareError: "hardware",
    E.InternalError: "internal",
}
_ERROR_OF_CODE = {code: cls for cls, code in ERROR_CODE_OF.items()}


class ProtocolError(E.LikenessError):
    """An error whose protocol code was decided where it was found (the request schema's checks); prefer raising
    the typed errors of :mod:`models.errors`."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def code_of(exc: BaseException) -> str:
    """The protocol error code of ``exc``: from :data:`ERROR_CODE_OF` (nearest listed base), ``internal`` else."""
    if isinstance(exc, ProtocolError):
        return exc.code
    for cls in type(exc).__mro__:
        code = ERROR_CODE_OF.get(cls)  # type: ignore[call-overload]
        if code is not None:
            return code
    return "internal"


def error_for(code: str, message: str) -> E.LikenessError:
    """The typed error a protocol code stands for (a client turning an error reply back into an exception)."""
    return _ERROR_OF_CODE.get(code, E.InternalError)(message)


def error_body(exc: BaseException) -> dict[str, str]:
    """``{"code", "message"}`` of an error reply for ``exc``."""
    message = exc.message if isinstance(exc, E.LikenessError) else f"{type(exc).__name__}: {exc}"
    return {"code": code_of(exc), "message": message[:1000]}


def reply_for(rid: Any, exc: BaseException) -> dict[str, Any]:
    """The error reply to request ``rid`` for ``exc``."""
    return {"id": rid, "ok": False, "error": error_body(exc)}


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def error_reply(rid: Any, code: str, message: str) -> dict[str, Any]:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message[:1000]}}
