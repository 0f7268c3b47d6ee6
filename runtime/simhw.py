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


def start(
    driver: str,
    bus_name: str,
    options: Mapping[str, Any],
    motors: Sequence[MotorConfig],
    initial: Mapping[str, float] | None = None,
) -> SimBus:
    """Start the emulator of ``driver`` serving ``motors``, each starting at ``initial[name]`` (SI, default 0).

    ConfigError for a driver without an emulator.
    """
    try:
        starter = _STARTERS[driver]
    except KeyError:
        raise ConfigError(f"buses.{bus_name}.simulated", f"no emulator for driver {driver!r}") from None
    start_counts = {m.device_id: m.to_counts((initial or {}).get(m.name, 0.0)) for m in motors}
    return starter(bus_name, dict(options), list(motors), start_counts)


def _start_canopen(
    bus_name: str, options: dict[str, Any], motors: list[MotorConfig], start_counts: dict[int, int]
) -> SimBus:
    from sim_hardware.canopen.network import DriveSet

    options["interface"] = "virtual"
    # A private channel per emulator, so several heads (or tests) in one process never share a bus.
    options["channel"] = f"{options.get('channel', bus_name)}-{os.getpid()}-{next(_unique)}"
    drives = DriveSet([m.device_id for m in motors], channel=options["channel"], interface="virtual",
                      initial_positions={k: float(v) for k, v in start_counts.items()})
    drives.start()

    def positions() -> dict[int, float]:
        return {nid: float(d.position_counts) for nid, d in drives.drives.items()}

    return SimBus(options, drives, positions, drives.stop)


def _start_dynamixel(
    bus_name: str, options: dict[str, Any], motors: list[MotorConfig], start_counts: dict[int, int]
) -> SimBus:
    from sim_hardware.dynamixel.server import DynamixelEmulator

    model = options.get("model", "XM430-W350")
    emu = DynamixelEmulator([m.device_id for m in motors], model=model, initial_positions=start_counts)
    emu.start()
    options["port"] = emu.port
    return SimBus(options, emu, emu.positions, emu.close)


_STARTERS: dict[str, Callable[[str, dict[str, Any], list[MotorConfig], dict[int, int]], SimBus]] = {
    "canopen402": _start_canopen,
    "dynamixel": _start_dynamixel,
}
