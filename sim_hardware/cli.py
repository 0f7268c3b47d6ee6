"""``likeness sim ...``: serve emulated motor buses and devices to other processes."""

from __future__ import annotations

import argparse
import importlib

#: Modules that add ``likeness sim`` subcommands through ``register(subparsers)``.
SIM_COMMAND_MODULES: tuple[str, ...] = (
    "sim_hardware.dynamixel.cli",
    "sim_hardware.canopen.cli",
    "sim_hardware.inject_cli",
    "sim_hardware.tracker_cli",
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``sim`` command group."""
    parser = sub.add_parser("sim", help="serve emulated hardware (CANopen drives, Dynamixel servos)")
    sim_sub = parser.add_subparsers(dest="sim_command", metavar="DEVICE")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])
    for name in SIM_COMMAND_MODULES:
        importlib.import_module(name).register(sim_sub)
