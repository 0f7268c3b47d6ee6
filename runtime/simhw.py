"""In-process emulated buses for heads whose config says ``simulated = true``.

Each adapter starts the emulator of one driver (``sim_hardware``, imported here only), rewrites the bus options so
the real driver connects to it (a private python-can ``virtual`` channel; the emulator's pseudo-terminal), and exposes
ground-truth positions in encoder counts by device id.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.base import MotorConfig
from drivers.errors import ConfigError

_unique = itertools.count(1)


@dataclass
class SimBus:
    """A running emulator: the options the driver must use, the emulator object and its ground truth."""

    options: dict[str, Any]
    emulator: Any
    positions_counts: Callable[[], dict[int, float]]
    close: Callable[[], None]


def start(driver: str, bus_name: str, options: Mapping[str, Any], motors: Sequence[MotorConfig]) -> SimBus:
    """Start the emulator of ``driver`` serving ``motors``; ConfigError for a driver without an emulator."""
    try:
        starter = _STARTERS[driver]
    except KeyError:
        raise ConfigError(f"buses.{bus_name}.simulated", f"no emulator for driver {driver!r}") from None
    return starter(bus_name, dict(options), list(motors))


def _start_canopen(bus_name: str, options: dict[str, Any], motors: list[MotorConfig]) -> SimBus:
    from sim_hardware.canopen import DriveSet

    options["interface"] = "virtual"
    # A private channel per emulator, so several heads (or tests) in one process never share a bus.
    options["channel"] = f"{options.get('channel', bus_name)}-{os.getpid()}-{next(_unique)}"
    drives = DriveSet(channel=options["channel"], interface="virtual", node_ids=[m.device_id for m in motors])
    drives.start()

    def positions() -> dict[int, float]:
        return {nid: float(d.position_counts) for nid, d in drives.drives.items()}

    return SimBus(options, drives, positions, drives.close)


def _start_dynamixel(bus_name: str, options: dict[str, Any], motors: list[MotorConfig]) -> SimBus:
    from sim_hardware.dynamixel import DynamixelEmulator

    model = options.get("model", "XM430-W350")
    emu = DynamixelEmulator(ids=[m.device_id for m in motors], model=model)
    emu.start()
    options["port"] = emu.port

    def positions() -> dict[int, float]:
        return {i: float(s.position_counts) for i, s in emu.servos.items()}

    return SimBus(options, emu, positions, emu.close)


_STARTERS: dict[str, Callable[[str, dict[str, Any], list[MotorConfig]], SimBus]] = {
    "canopen402": _start_canopen,
    "dynamixel": _start_dynamixel,
}
