"""The core's ports: what one cycle takes in and what it asks the world to do.

The runner builds :class:`CycleInputs` (bus feedback, commands, outcomes of bus requests, an out-of-band e-stop) and
carries out :class:`CycleOutputs` (targets to post, bus requests, replies, events, telemetry, recorded rows); the
core's systems only append to the outputs. Replies, events and telemetry reach the API server as maps (``Body``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, TypeAlias

import numpy as np

from models.protocol import error_body
from runtime.core.commands import Command
from runtime.core.events import Body, Event

#: A bus lifecycle request, carried out by the bus's process.
BusOp: TypeAlias = Literal["enable", "disable", "reset"]
#: The outcome of a finished bus request: (bus, op, ok, message).
BusResult: TypeAlias = tuple[str, str, bool, str]


@dataclass(frozen=True)
class BusInput:
    """One bus's latest feedback, as the runner read it (SI, this bus's actuators in order)."""

    name: str
    state: str  # drivers.base.LifecycleState value
    connected: bool
    positions: np.ndarray
    stamp: float  # when the sample was taken (monotonic)
    faults: dict[str, tuple[int, str]] = field(default_factory=dict)
    #: one of runtime.bus.layout.CONNECTION_STATES ("" when the source does not say: taken from ``connected``)
    connection: str = ""
    attempts: int = 0  # reconnect attempts since the connection was lost
    retry_at: float = float("inf")  # when the bus process tries to reconnect next (monotonic)
    #: the last targets the bus wrote (after an enable: the positions its motors hold); None when not known
    written: np.ndarray | None = None


@dataclass(frozen=True)
class CycleInputs:
    """Everything a cycle depends on."""

    t: float
    buses: tuple[BusInput, ...]
    commands: tuple[Command, ...] = ()
    results: tuple[BusResult, ...] = ()  # finished bus requests
    estop: str | None = None  # an out-of-band e-stop (shared flag, signal): its reason
    between_cycles: bool = False  # commands taken between two cycles (no read, no write)


@dataclass
class CycleOutputs:
    """What a cycle asks the world to do."""

    write: np.ndarray | None = None  # commanded positions (SI) to post to the buses, None: write nothing
    bus_requests: list[tuple[str, BusOp]] = field(default_factory=list)
    replies: list[tuple[int, Body]] = field(default_factory=list)  # (token, body or {"error": ...})
    events: list[Body] = field(default_factory=list)  # each an Event's map (the server takes maps)
    telemetry: Body | None = None
    record: np.ndarray | None = None  # rows [t, commanded..., measured...] recorded since the last output

    def emit(self, event: Event) -> None:
        """Publish ``event``."""
        self.events.append(event.as_dict())

    def reply(self, token: int, body: Body) -> None:
        """Answer the command ``token`` with ``body``."""
        self.replies.append((token, body))

    def refuse(self, token: int, exc: BaseException) -> None:
        """Answer the command ``token`` with the error ``exc`` (its protocol code and message)."""
        self.replies.append((token, {"error": error_body(exc)}))

    def request(self, bus: str, op: BusOp) -> None:
        """Ask ``bus`` for a lifecycle transition."""
        self.bus_requests.append((bus, op))
