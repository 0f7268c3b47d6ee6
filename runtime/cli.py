"""Runtime commands: the daemon and its clients (``demo``, ``daemon``, ``stream``, ``status``, ``estop``...)."""

from __future__ import annotations

import argparse
import importlib

#: Modules that add top-level runtime subcommands through ``register(subparsers)``.
RUNTIME_COMMAND_MODULES: tuple[str, ...] = (
    "runtime.commands.demo",
    "runtime.commands.daemon",
    "runtime.commands.stream",
    "runtime.commands.status",
    "runtime.commands.keys",
    "runtime.commands.plot",
    "runtime.commands.recording",
    "offline.cli.calibrate",
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the runtime's top-level commands."""
    for name in RUNTIME_COMMAND_MODULES:
        importlib.import_module(name).register(sub)
