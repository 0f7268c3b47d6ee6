"""Commands the API server hands the control core, already decoded, validated and compiled (plain picklable data).

Every command carries the ``token`` its reply is matched by. Values are SI or channel-vector indices; nothing here
needs parsing in the loop. :data:`Command` is the union of them all: the core dispatches over it with ``match``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeAlias

import numpy as np

if TYPE_CHECKING:
    from runtime.core.clips import BoundClip


@dataclass(frozen=True)
class _Tokened:
    """What every command carries: the token its reply is matched by."""

    token: int


@dataclass(frozen=True)
class Enable(_Tokened):
    """Request every bus active (torque on); answered when all are."""


@dataclass(frozen=True)
class Disable(_Tokened):
    """Torque off: every active bus to inactive; answered when they are."""


@dataclass(frozen=True)
class EStop(_Tokened):
    """Latch the e-stop (preempts whatever else is queued with it)."""

    reason: str = "api"


@dataclass(frozen=True)
class Reset(_Tokened):
    """Leave FAULT or e-stop for inactive: resets the buses that need it."""


@dataclass(frozen=True)
class Status(_Tokened):
    """A snapshot of the core (lifecycle, sources, guard, recording)."""


@dataclass(frozen=True)
class LoadClip(_Tokened):
    """Add or replace a clip on the timeline, within the clip memory budget."""

    clip: BoundClip  # compiled and bound to the channel vector by the API server
    key_count: int = 0
    nbytes: int = 0


@dataclass(frozen=True)
class UnloadClip(_Tokened):
    """Remove a loaded clip (stopping it if it plays)."""

    name: str = ""


@dataclass(frozen=True)
class Play(_Tokened):
    """Play a loaded clip from clip time ``offset`` at daemon time ``at`` (now if None)."""

    name: str = ""
    at: float | None = None
    offset: float = 0.0
    speed: float = 1.0
    loop: bool = False
    source: str = "api"  # the input that asked (status and telemetry say which source drives)


@dataclass(frozen=True)
class Pause(_Tokened):
    """Pause the playing clip where it is."""


@dataclass(frozen=True)
class Resume(_Tokened):
    """Resume the paused clip."""


@dataclass(frozen=True)
class StopMotion(_Tokened):
    """Stop every source: the head holds where it is."""


@dataclass(frozen=True)
class Seek(_Tokened):
    """Move the playing clip to clip time ``time``."""

    time: float = 0.0


@dataclass(frozen=True)
class Stream(_Tokened):
    """Timestamped frames for the jitter buffer (rows of channel values)."""

    times: np.ndarray = field(default_factory=lambda: np.empty(0))
    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))  # channel indices
    rows: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))  # frames × channels, config units
    received: float | None = None  # when the request reached the daemon: lateness is judged against it


@dataclass(frozen=True)
class Pose(_Tokened):
    """Move to a pose (channel values) at a fraction ``speed`` of the limits."""

    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    values: np.ndarray = field(default_factory=lambda: np.empty(0))
    speed: float = 0.25


@dataclass(frozen=True)
class Record(_Tokened):
    """Start or stop recording commanded and measured positions."""

    action: str = "start"  # "start" | "stop"
    name: str = "recording"


@dataclass(frozen=True)
class Live(_Tokened):
    """Values from a show-control input (OSC, sACN): set ``channels`` to ``values`` (config units) now, or at daemon
    time ``at`` (an OSC bundle's timetag), all in the same cycle."""

    source: str = "osc"
    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    values: np.ndarray = field(default_factory=lambda: np.empty(0))
    at: float | None = None
    received: float | None = None
    takeover: bool = True  # False: keeps an active live source alive without taking over (sACN repeats)
    watchdog_s: float | None = None  # silence before the watchdog holds (None: [safety] watchdog_hold_s)
    quiet: bool = False  # answered only when refused: a show-control packet, whose sender waits for no reply

    def __reduce__(self) -> tuple[object, tuple[object, ...]]:
        """Pickled with its two small arrays as raw bytes: every OSC or sACN packet crosses the command pipe as one
        of these, and numpy's own pickling of a one-element array costs about ten times as much each way."""
        return _live_from_wire, (self.token, self.source, *_wire_array(self.channels), *_wire_array(self.values),
                                 self.at, self.received, self.takeover, self.watchdog_s, self.quiet)


def _wire_array(a: np.ndarray) -> tuple[str, tuple[int, ...], bytes]:
    a = np.ascontiguousarray(a)
    return a.dtype.str, a.shape, a.tobytes()


def _live_from_wire(token: int, source: str, c_dtype: str, c_shape: tuple[int, ...], c_bytes: bytes, v_dtype: str,
                    v_shape: tuple[int, ...], v_bytes: bytes, at: float | None, received: float | None,
                    takeover: bool, watchdog_s: float | None, quiet: bool = False) -> Live:
    """A :class:`Live` from its pickled form (:meth:`Live.__reduce__`); its arrays are read-only views of the
    bytes."""
    return Live(token, source, np.frombuffer(c_bytes, c_dtype).reshape(c_shape),
                np.frombuffer(v_bytes, v_dtype).reshape(v_shape), at, received, takeover, watchdog_s, quiet)


@dataclass(frozen=True)
class Timecode(_Tokened):
    """A timecode sample: ``seconds`` of timecode as of daemon time ``received``; ``full``: a full-frame locate."""

    seconds: float = 0.0
    fps: float = 30.0
    rate: str = "30"
    label: str = ""
    received: float = 0.0
    full: bool = False


#: Every command the core takes (annotate with this; the core's dispatch covers each kind).
Command: TypeAlias = (Enable | Disable | EStop | Reset | Status | LoadClip | UnloadClip | Play | Pause | Resume
                      | StopMotion | Seek | Stream | Pose | Record | Live | Timecode)
