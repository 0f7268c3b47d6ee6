"""Emulated Dynamixel protocol 2.0 servos served on a pseudo-terminal (see :mod:`.server`)."""

from __future__ import annotations

from sim_hardware.dynamixel.server import DynamixelEmulator, parse_ids

__all__ = ["DynamixelEmulator", "parse_ids"]
