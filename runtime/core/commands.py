"""Commands the API server hands the control core, already decoded, validated and compiled (plain picklable data).

Every command carries the ``token`` its reply is matched by. Values are SI or channel-vector indices; nothing here
needs parsing in the loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Command:
    token: int


@dataclass(frozen=True)
class Enable(Command):
    pass


@dataclass(frozen=True)
class Disable(Command):
    pass


@dataclass(frozen=True)
class EStop(Command):
    reason: str = "api"


@dataclass(frozen=True)
class Reset(Command):
    pass


@dataclass(frozen=True)
class Status(Command):
    pass


@dataclass(frozen=True)
class LoadClip(Command):
    clip: Any = None  # a compiled clip: name, duration, channels (indices), sample_into(t, out)
    key_count: int = 0
    nbytes: int = 0


@dataclass(frozen=True)
class UnloadClip(Command):
    name: str = ""


@dataclass(frozen=True)
class Play(Command):
    name: str = ""
    at: float | None = None
    offset: float = 0.0
    speed: float = 1.0
    loop: bool = False
    source: str = "api"  # the input that asked (status and telemetry say which source drives)


@dataclass(frozen=True)
class Pause(Command):
    pass


@dataclass(frozen=True)
class Resume(Command):
    pass


@dataclass(frozen=True)
class StopMotion(Command):
    pass


@dataclass(frozen=True)
class Seek(Command):
    time: float = 0.0


@dataclass(frozen=True)
class Stream(Command):
    times: np.ndarray = field(default_factory=lambda: np.empty(0))
    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))  # channel indices
    rows: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))  # frames × channels, config units
    received: float | None = None  # when the request reached the daemon: lateness is judged against it


@dataclass(frozen=True)
class Pose(Command):
    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    values: np.ndarray = field(default_factory=lambda: np.empty(0))
    speed: float = 0.25


@dataclass(frozen=True)
class Record(Command):
    action: str = "start"  # "start" | "stop"
    name: str = "recording"


@dataclass(frozen=True)
class Live(Command):
    """Values from a show-control input (OSC, sACN): set ``channels`` to ``values`` (config units) now, or at daemon
    time ``at`` (an OSC bundle's timetag), all in the same cycle."""

    source: str = "osc"
    channels: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.intp))
    values: np.ndarray = field(default_factory=lambda: np.empty(0))
    at: float | None = None
    received: float | None = None
    takeover: bool = True  # False: keeps an active live source alive without taking over (sACN repeats)
    watchdog_s: float | None = None  # silence before the watchdog holds (None: [safety] watchdog_hold_s)


@dataclass(frozen=True)
class Timecode(Command):
    """A timecode sample: ``seconds`` of timecode as of daemon time ``received``; ``full``: a full-frame locate."""

    seconds: float = 0.0
    fps: float = 30.0
    rate: str = "30"
    label: str = ""
    received: float = 0.0
    full: bool = False
