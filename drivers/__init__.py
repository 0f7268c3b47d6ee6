"""Motor buses behind one ABC: CANopen CiA 402 drives and Dynamixel 2.0 servos, selected by name."""

from drivers.base import LifecycleState, MotorBus, MotorConfig, MotorState
from drivers.errors import (
    BusError,
    BusInitError,
    BusTimeout,
    CommandRejected,
    ConfigError,
    DeviceFault,
    LifecycleError,
)
from drivers.registry import available_backends, create_bus

__all__ = [
    "BusError",
    "BusInitError",
    "BusTimeout",
    "CommandRejected",
    "ConfigError",
    "DeviceFault",
    "LifecycleError",
    "LifecycleState",
    "MotorBus",
    "MotorConfig",
    "MotorState",
    "available_backends",
    "create_bus",
]
