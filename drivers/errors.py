"""Typed errors of the motor-bus layer, so callers can tell a bad config from a dead device."""

from __future__ import annotations


class BusError(Exception):
    """Base class of every motor-bus error."""


class ConfigError(BusError, ValueError):
    """A bus or motor configuration is invalid; the message names the key and the bad value."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key


class BusInitError(BusError):
    """The bus or one of its devices could not be opened or configured."""


class BusTimeout(BusError):
    """A device did not answer in time; ``device`` names it (motor name or id)."""

    def __init__(self, device: str, message: str) -> None:
        super().__init__(f"{device}: {message}")
        self.device = device


class DeviceFault(BusError):
    """A device reported a fault (EMCY, hardware error, lost heartbeat); ``code`` is device-specific."""

    def __init__(self, device: str, code: int, message: str) -> None:
        super().__init__(f"{device}: fault 0x{code:04X}: {message}")
        self.device = device
        self.code = code


class BusConnectionLost(BusError):
    """The bus's transport is gone (socketcand connection dropped, serial port or pseudo-terminal vanished): the bus
    must be closed and opened again once it is reachable."""


class LifecycleError(BusError):
    """The operation is not allowed in the bus's current lifecycle state."""


class CommandRejected(BusError):
    """A command was refused before reaching the bus (unknown motor, NaN, outside limits or rates)."""
