"""``likeness offline ...``: design-time tools (meshing, FEM, material fitting, datasets, training)."""

from __future__ import annotations

import argparse
import importlib

#: Modules that add ``likeness offline`` subcommands through ``register(subparsers)``.
OFFLINE_COMMAND_MODULES: tuple[str, ...] = (
    "offline.mesh.cli",
    "offline.fem_cli",
    "offline.design.cli",
    "offline.design.clone_cli",
    "offline.material.cli",
    "offline.dataset.cli",
    "offline.train.cli",
    "offline.train.evaluate_cli",
    "offline.guard_cli",
    "offline.refinement_cli",
    "offline.active.cli",
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``offline`` command group."""
    parser = sub.add_parser("offline", help="design-time tools: mesh, simulate, fit materials, train")
    off_sub = parser.add_subparsers(dest="offline_command", metavar="TOOL")
    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])
    for name in OFFLINE_COMMAND_MODULES:
        importlib.import_module(name).register(off_sub)
