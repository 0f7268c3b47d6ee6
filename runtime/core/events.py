"""The events the core publishes, one frozen dataclass per kind; :data:`Event` is their union.

The API server takes events as maps today: :meth:`as_dict` gives each one's map, in the shape the protocol publishes
(``{"event": kind, "t": ..., ...}``), and :meth:`runtime.core.cycle.CycleOutputs.emit` hands that over.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeAlias

#: A map as the API server takes it: a reply body, an event or a telemetry snapshot (SI arrays, formatted there).
Body: TypeAlias = dict[str, object]


@dataclass(frozen=True)
class LifecycleChanged:
    """The head's lifecycle changed (``state`` and ``previous`` are :class:`~runtime.core.lifecycle.Lifecycle`
    values)."""

    t: float
    state: str
    previous: str

    def as_dict(self) -> Body:
        """The ``lifecycle`` event."""
        return {"event": "lifecycle", "t": self.t, "state": self.state, "previous": self.previous}


@dataclass(frozen=True)
class Fault:
    """Why the head entered FAULT: what found it, its message, the bus (if one), and every device fault then."""

    source: str  # "bus", "driver", "timeout", "following_error", "control loop"
    message: str
    t: float
    bus: str | None
    faults: dict[str, list[int | str]]  # "bus/device" → [code, message]
    actuator: str | None = None  # the actuator that stopped following ("following_error")

    def info(self) -> Body:
        """The fault as status replies report it."""
        return {"source": self.source, "message": self.message, "t": self.t, "bus": self.bus,
                "actuator": self.actuator, "faults": self.faults}

    def as_dict(self) -> Body:
        """The ``fault`` event."""
        return {"event": "fault", **self.info()}


@dataclass(frozen=True)
class EStopped:
    """The e-stop latched, with its reason."""

    t: float
    reason: str

    def as_dict(self) -> Body:
        """The ``estop`` event."""
        return {"event": "estop", "t": self.t, "reason": self.reason}


@dataclass(frozen=True)
class BusConnectionChanged:
    """A bus's connection changed (``lost``, ``reconnecting``, ``connected``...)."""

    t: float
    bus: str
    state: str
    previous: str
    attempts: int
    retry_in_s: float | None

    def as_dict(self) -> Body:
        """The ``bus_link`` event."""
        return {"event": "bus_link", "t": self.t, "bus": self.bus, "state": self.state, "previous": self.previous,
                "attempts": self.attempts, "retry_in_s": self.retry_in_s}


@dataclass(frozen=True)
class FeedbackLate:
    """A bus's devices have not reported for longer than ``[buses.NAME] feedback_timeout_s`` (``state`` ``late``,
    ``age`` the age then), or have reported within it again for a while (``recovered``, ``age`` the largest age
    seen)."""

    t: float
    bus: str
    state: str  # "late" or "recovered"
    age: float
    limit: float

    def as_dict(self) -> Body:
        """The ``feedback_late`` event."""
        return {"event": "feedback_late", "t": self.t, "bus": self.bus, "state": self.state, "age": self.age,
                "limit": self.limit}


@dataclass(frozen=True)
class BusRequestFailed:
    """A bus refused a lifecycle request no transition waits for."""

    t: float
    bus: str
    op: str
    message: str

    def as_dict(self) -> Body:
        """The ``bus`` event."""
        return {"event": "bus", "t": self.t, "bus": self.bus, "op": self.op, "ok": False, "message": self.message}


@dataclass(frozen=True)
class ClipPlaying:
    """A clip starts playing (clip time 0 at daemon time ``start``); ``source`` only when the timecode started it."""

    t: float
    clip: str
    start: float
    source: str | None = None

    def as_dict(self) -> Body:
        """The ``clip`` event, state ``playing``."""
        body: Body = {"event": "clip", "t": self.t, "state": "playing", "clip": self.clip, "start": self.start}
        if self.source is not None:
            body["source"] = self.source
        return body


@dataclass(frozen=True)
class ClipFinished:
    """The playing clip reached its end (not looping)."""

    t: float
    clip: str

    def as_dict(self) -> Body:
        """The ``clip`` event, state ``finished``."""
        return {"event": "clip", "t": self.t, "state": "finished", "clip": self.clip}


@dataclass(frozen=True)
class Watchdog:
    """A stream or live source went silent: ``hold`` where it is, then ease to ``neutral``."""

    t: float
    stage: str
    age: float
    source: str | None

    def as_dict(self) -> Body:
        """The ``watchdog`` event."""
        return {"event": "watchdog", "t": self.t, "stage": self.stage, "age": self.age, "source": self.source}


@dataclass(frozen=True)
class DroppedFrames:
    """Stream frames arrived behind the play-out point (``total``: since start)."""

    t: float
    late: int
    total: int

    def as_dict(self) -> Body:
        """The ``dropped_frames`` event."""
        return {"event": "dropped_frames", "t": self.t, "late": self.late, "total": self.total}


@dataclass(frozen=True)
class TimecodeChanged:
    """The timecode chase changed state (``change``: ``lock``, ``jump``, ``freewheel``, ``hold``...)."""

    t: float
    state: str
    change: str
    timecode: str
    rate: str

    def as_dict(self) -> Body:
        """The ``timecode`` event."""
        return {"event": "timecode", "t": self.t, "state": self.state, "change": self.change,
                "timecode": self.timecode, "rate": self.rate}


@dataclass(frozen=True)
class RecordStarted:
    """A recording started."""

    t: float
    name: str

    def as_dict(self) -> Body:
        """The ``record`` event, state ``started``."""
        return {"event": "record", "t": self.t, "state": "started", "name": self.name}


@dataclass(frozen=True)
class RecordStopped:
    """A recording stopped after ``samples`` rows."""

    t: float
    name: str
    samples: int

    def as_dict(self) -> Body:
        """The ``record`` event, state ``stopped``."""
        return {"event": "record", "t": self.t, "state": "stopped", "name": self.name, "samples": self.samples}


@dataclass(frozen=True)
class OutOfRange:
    """An actuator enabled where it stood outside its configured limits (``state`` ``outside``: it is being brought
    back at safe speed, never further out) or back inside them (``inside``); ``position`` and the limits in its
    config unit."""

    t: float
    actuator: str
    state: str  # "outside" or "inside"
    position: float
    min: float
    max: float
    unit: str

    def as_dict(self) -> Body:
        """The ``out_of_range`` event."""
        return {"event": "out_of_range", "t": self.t, "actuator": self.actuator, "state": self.state,
                "position": self.position, "min": self.min, "max": self.max, "unit": self.unit}


#: Every event the core publishes.
Event: TypeAlias = (LifecycleChanged | Fault | EStopped | BusConnectionChanged | FeedbackLate | BusRequestFailed
                    | ClipPlaying | ClipFinished | Watchdog | DroppedFrames | TimecodeChanged | RecordStarted
                    | RecordStopped | OutOfRange)
