"""The project's one error hierarchy: what went wrong, by kind, whoever reports it.

:class:`LikenessError` is the root. :class:`SpecError` is an invalid file crossing the offline/runtime boundary
(head spec, link map, predictor, data file). The rest are the runtime's kinds: the control core, the API server and
the request decoder raise them; each kind is mapped once to a protocol error code
(:data:`models.protocol.ERROR_CODE_OF`, used for every error reply) and once to a command-line exit status
(:data:`likeness.cli.EXIT_STATUS`). The drivers keep their own hierarchy (``drivers.errors.BusError``: they know
nothing of heads); the exit-status table names it too.
"""

from __future__ import annotations

from typing import Any

_MISSING = object()


class LikenessError(Exception):
    """Base of the project's errors; ``message`` is the one line shown to the client or operator."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class BadRequest(LikenessError):
    """A request that is not a valid message: not a map, missing or mistyped fields, unknown fields, too deep."""


class UnknownOp(BadRequest):
    """A request names an operation the daemon does not have."""


class BadValue(LikenessError):
    """A value out of range, not finite, or a malformed clip."""


class UnknownChannel(BadValue):
    """A channel name the head does not have."""


class NotFound(LikenessError):
    """A clip or recording that is not known."""


class BadState(LikenessError):
    """The operation is not allowed in the head's present lifecycle state."""


class EStopLatched(BadState):
    """The e-stop is latched: only status, hello, clock and reset are served."""


class Faulted(BadState):
    """The head is in FAULT: reset first."""


class TooLarge(LikenessError):
    """A request, clip or buffer exceeds a configured limit."""


class HardwareError(LikenessError):
    """A bus refused or failed a lifecycle transition (enable, disable, reset), or is not connected."""


class ConfigError(LikenessError):
    """A head config or asset is invalid; the message names the file and key."""


class StartError(LikenessError):
    """The daemon could not start (a bus, the API server or the loop); the message says which and why."""


class UsageError(LikenessError):
    """A command line that cannot run: an option out of range, options that do not go together, a missing input."""


class InternalError(LikenessError):
    """A bug: an operation raised something unexpected. The daemon lives on."""


class SpecError(LikenessError, ValueError):
    """An invalid head spec, link map, predictor or data file; names the file, key and bad value."""

    def __init__(self, source: str, key: str, message: str, value: Any = _MISSING) -> None:
        text = f"{source}: {key}: {message}"
        if value is not _MISSING:
            text += f" (got {value!r})"
        super().__init__(text)
        self.source = source
        self.key = key
