"""The ``likeness`` command: one entry point whose subcommands live with the package that owns them.

Each module listed in :data:`COMMAND_MODULES` exposes ``register(subparsers)`` and adds its
subcommands, each with ``set_defaults(func=...)``; ``func(args)`` returns the exit status.
Command modules import only the standard library at module level, so ``likeness --help``
stays fast and a runtime install never loads offline dependencies.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from likeness import __version__

#: Modules that contribute subcommands, in help order.
COMMAND_MODULES: tuple[str, ...] = (
    "runtime.cli",
    "sim_hardware.cli",
    "offline.cli",
    "studio.cli",
)


class CliError(Exception):
    """A user-facing error: printed as one line without a traceback; the process exits with ``status`` (default 2,
    a usage or configuration error; the runtime's commands choose it from the kind of error, see
    ``runtime.commands._common.EXIT_STATUS``)."""

    def __init__(self, message: str, status: int = 2) -> None:
        super().__init__(message)
        self.status = status


def build_parser() -> argparse.ArgumentParser:
    """Build the full argument parser from every command module."""
    parser = argparse.ArgumentParser(
        prog="likeness",
        description="Likeness: skin simulation, learned predictors and the realtime head daemon.",
    )
    parser.add_argument("--version", action="version", version=f"likeness {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="likeness_command", metavar="COMMAND")  # not "command": a subcommand has --command
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        return int(func(args) or 0)
    except CliError as exc:
        print(f"likeness {args.likeness_command}: error: {exc}", file=sys.stderr)
        return exc.status
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    # Run through the imported module, not this ``__main__`` copy: command modules raise ``likeness.cli.CliError``,
    # a different class from ``__main__.CliError``, which would escape as a traceback.
    from likeness.cli import main as _main

    raise SystemExit(_main())
