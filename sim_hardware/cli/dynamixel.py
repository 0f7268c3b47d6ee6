"""``likeness sim dynamixel``: serve emulated Dynamixel servos on a pseudo-terminal until stopped.

Prints one ``ready:`` line once the pty and the optional fault-injection control endpoint are
up, then serves until SIGINT or SIGTERM and removes the ``--link`` symlink on the way out.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sim_hardware.cli._server import StopSignals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The servos, the pty link and the emulation's settings."""
    parser.description = "Serve emulated Dynamixel servos on a pty; PATH becomes a symlink to the device."
    parser.add_argument("--ids", default="1-13", help="servo ids, e.g. 1-13 or 1,3,5-7 (default 1-13)")
    parser.add_argument("--model", default="XM430-W350", help="servo model (default XM430-W350)")
    parser.add_argument("--link", required=True, metavar="PATH", help="symlink to create to the pty device")
    parser.add_argument("--control", metavar="ENDPOINT", help="ZeroMQ endpoint for fault injection, e.g. tcp://127.0.0.1:5590")
    parser.add_argument("--initial-position", type=int, default=0, metavar="COUNTS",
                        help="Present Position of every servo at start (default 0)")
    parser.add_argument("--initial-positions", default="", metavar="ID=COUNTS,...",
                        help="Present Position of single servos, e.g. 1=2048,3=1000 (overrides --initial-position)")
    parser.add_argument("--seed", type=int, default=None, help="random seed of the packet fault injector")
    parser.add_argument("--watch-parent", action="store_true",
                        help="exit when the process that started this one exits")


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM; exit 0."""
    from sim_hardware.cli._server import StopSignals

    ids, link, initial = _checked(args)
    with StopSignals(args.watch_parent) as signals:
        _serve(args, ids, link, initial, signals)
    return 0


def _checked(args: argparse.Namespace) -> tuple[list[int], str, dict[int, int]]:
    """The servo ids, the absolute link path and each servo's start position (UsageError naming a bad option)."""
    import os

    from models.errors import UsageError
    from sim_hardware.cli._server import parse_counts
    from sim_hardware.dynamixel.control_table import MODELS
    from sim_hardware.dynamixel.server import parse_ids

    try:
        ids = parse_ids(args.ids)
    except ValueError as exc:
        raise UsageError(f"--ids: {exc}") from None
    if args.model not in MODELS:
        raise UsageError(f"--model: unknown model {args.model!r}; known: {', '.join(sorted(MODELS))}")
    link = os.path.abspath(args.link)
    if os.path.exists(link) and not os.path.islink(link):
        raise UsageError(f"--link: {link} exists and is not a symlink; refusing to replace it")
    if not os.path.isdir(os.path.dirname(link)):
        raise UsageError(f"--link: directory {os.path.dirname(link)} does not exist")

    try:
        single = {k: round(v) for k, v in parse_counts(args.initial_positions).items()}
    except ValueError as exc:
        raise UsageError(f"--initial-positions: {exc}") from None
    unknown = sorted(set(single) - set(ids))
    if unknown:
        raise UsageError(f"--initial-positions: servo ids {unknown} are not among --ids {args.ids}")
    return ids, link, {i: single.get(i, args.initial_position) for i in ids}


def _serve(args: argparse.Namespace, ids: list[int], link: str, initial: dict[int, int],
           signals: StopSignals) -> None:
    """Run the emulator on its pty (``link`` points at it) and the control endpoint until ``signals`` says stop."""
    from models.errors import UsageError
    from sim_hardware.dynamixel.server import DynamixelEmulator

    emulator = DynamixelEmulator(ids, args.model, initial_positions=initial, seed=args.seed)
    control = None
    try:
        emulator.start()
        emulator.link(link)
        if args.control:
            from models.emulator_control import ControlServer

            try:
                control = ControlServer(args.control, emulator.handle_control)
            except Exception as exc:
                raise UsageError(f"--control: cannot bind {args.control}: {exc}") from None
        span = f"ids {args.ids}"
        extra = f", control {control.endpoint}" if control else ""
        print(f"ready: {len(ids)} {args.model} servos ({span}) on {link} -> {emulator.port}{extra}", flush=True)
        signals.wait()
    finally:
        if control is not None:
            control.close()
        emulator.close()
