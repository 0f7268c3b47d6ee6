"""The typed messages on a bus process's control pipe, and how a driver error crosses it.

The loop side sends :class:`OpRequest` (a lifecycle operation with a ticket) or :class:`StopRequest`; the bus process
answers once with :class:`Opened` after start-up, then one :class:`OpResult` per request. A driver's typed error
travels as an :class:`ErrorInfo` and is rebuilt on the loop side, so ``start`` raises what the driver raised.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

from drivers import errors as bus_errors
from drivers.errors import BusInitError

#: A lifecycle operation the loop side may ask of a bus process (``reset`` clears a fault or reconnects).
BusOp = Literal["enable", "disable", "reset"]
BUS_OPS: tuple[BusOp, ...] = get_args(BusOp)

#: The scalar attributes of an exception that travel with it (device names, codes).
ErrorAttrs = dict[str, str | int | float]


@dataclass(frozen=True, slots=True)
class ErrorInfo:
    """An exception as data: where its class lives, its name, message and scalar attributes."""

    module: str
    name: str
    message: str
    attrs: ErrorAttrs = field(default_factory=dict)

    @classmethod
    def describe(cls, exc: BaseException) -> ErrorInfo:
        """The parts of ``exc`` that can be sent to another process."""
        attrs: ErrorAttrs = {k: v for k, v in vars(exc).items() if isinstance(v, str | int | float)}
        return cls(type(exc).__module__, type(exc).__name__, str(exc), attrs)

    def rebuild(self, bus: str) -> Exception:
        """The driver's typed error again (a :class:`drivers.errors.BusError` kind); others as BusInitError."""
        cls = getattr(bus_errors, self.name, None) if self.module == bus_errors.__name__ else None
        if isinstance(cls, type) and issubclass(cls, bus_errors.BusError):
            exc = cls.__new__(cls)
            Exception.__init__(exc, self.message)
            exc.__dict__.update(self.attrs)
            return exc
        return BusInitError(f"bus {bus!r}: {self.name}: {self.message}")


@dataclass(frozen=True, slots=True)
class OpRequest:
    """Loop side → bus process: carry out ``op``; the answer names ``ticket``."""

    op: BusOp
    ticket: int


@dataclass(frozen=True, slots=True)
class StopRequest:
    """Loop side → bus process: torque off, close the bus and exit."""


@dataclass(frozen=True, slots=True)
class Opened:
    """Bus process → loop side, once: the bus opened (``error`` None) or why it did not."""

    error: ErrorInfo | None = None


@dataclass(frozen=True, slots=True)
class OpResult:
    """Bus process → loop side: the outcome of the request with ``ticket`` (``message`` says why it failed)."""

    ticket: int
    ok: bool
    message: str = ""


#: What the loop side sends to a bus process.
ToBusProcess = OpRequest | StopRequest
#: What a bus process sends to the loop side.
FromBusProcess = Opened | OpResult
