"""Lazy backend registry: backends are named in config and imported only when first used."""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from typing import Any

from drivers.base import MotorBus, MotorConfig
from drivers.errors import BusInitError, ConfigError

#: driver name → (module, class). Importing a backend loads its optional libraries.
BACKENDS: dict[str, tuple[str, str]] = {
    "canopen402": ("drivers.canopen402", "CanOpen402Bus"),
    "dynamixel": ("drivers.dynamixel", "DynamixelBus"),
}


def available_backends() -> list[str]:
    """Names accepted as a bus ``driver``."""
    return sorted(BACKENDS)


def backend_class(driver: str) -> type[MotorBus]:
    """Import and return the bus class registered as ``driver``."""
    try:
        module_name, class_name = BACKENDS[driver]
    except KeyError:
        raise ConfigError(
            "driver", f"unknown backend {driver!r}; available: {', '.join(available_backends())}"
        ) from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BusInitError(f"backend {driver!r} needs a library that is not installed: {exc}") from exc
    return getattr(module, class_name)


def create_bus(
    driver: str, name: str, options: Mapping[str, Any], motors: Sequence[MotorConfig]
) -> MotorBus:
    """Create (not open) a bus of the named backend."""
    return backend_class(driver)(name, options, motors)
