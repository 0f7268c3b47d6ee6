"""What a bus process is started with: its driver, the driver's options, its motors and its timing."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

from drivers.base import MotorConfig

#: A driver's options as the head config gives them (TOML values: strings, numbers, booleans, tables).
DriverOptions = Mapping[str, object]


@dataclass(frozen=True)
class BusProcessConfig:
    """Everything the bus process needs, sent to it once at spawn (pickled).

    ``idle_hz`` is the feedback rate while no targets arrive; ``realtime_priority`` asks for SCHED_FIFO (None:
    normal priority); ``write_priority`` > 0 (with ``realtime_priority`` None) runs the process at SCHED_FIFO within
    a CPU budget (:mod:`runtime.rtbudget`), so new targets are written as soon as they are posted; ``open_attempts``
    retries opening on a driver error; ``nice`` is added to the process's niceness; ``reconnect_base_s`` is the wait
    before the first reconnect attempt after a lost connection, doubling up to ``reconnect_max_s``.
    """

    driver: str
    name: str
    options: dict[str, object]
    motors: tuple[MotorConfig, ...]
    idle_hz: float = 100.0
    realtime_priority: int | None = None
    write_priority: int = 0
    open_attempts: int = 1
    nice: int = 0
    log_level: int = logging.WARNING  # the daemon's: the drivers' libraries chatter at INFO
    reconnect_base_s: float = 0.25
    reconnect_max_s: float = 4.0

    def __post_init__(self) -> None:
        """Refuse settings the bus process could not run with, naming the bus."""
        if not self.motors:
            raise ValueError(f"bus {self.name!r}: a bus process needs at least one motor")
        if not (math.isfinite(self.idle_hz) and self.idle_hz > 0):
            raise ValueError(f"bus {self.name!r}: idle_hz must be a positive number, got {self.idle_hz!r}")
        if self.realtime_priority is not None and not 1 <= self.realtime_priority <= 99:
            raise ValueError(f"bus {self.name!r}: realtime_priority must be 1..99, got {self.realtime_priority!r}")
