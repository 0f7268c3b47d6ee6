"""``likeness sim dynamixel``: serve emulated Dynamixel servos on a pseudo-terminal until stopped.

Prints one ``ready:`` line once the pty and the optional fault-injection control endpoint are
up, then serves until SIGINT or SIGTERM and removes the ``--link`` symlink on the way out.
"""

from __future__ import annotations

import argparse


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
    import os
    import signal
    import threading

    from models.errors import UsageError
    from sim_hardware.cli._server import ParentWatch, parse_counts
    from sim_hardware.dynamixel.control_table import MODELS
    from sim_hardware.dynamixel.server import DynamixelEmulator, parse_ids

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
    initial = {i: single.get(i, args.initial_position) for i in ids}
    watch = ParentWatch(args.watch_parent)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    emulator = DynamixelEmulator(ids, args.model, initial_positions=initial, seed=args.seed)
    control = None
    try:
        emulator.start()
        emulator.link(link)
        if args.control:
            from sim_hardware.control import ControlServer

            try:
                control = ControlServer(args.control, emulator.handle_control)
            except Exception as exc:
                raise UsageError(f"--control: cannot bind {args.control}: {exc}") from None
        span = f"ids {args.ids}"
        extra = f", control {control.endpoint}" if control else ""
        print(f"ready: {len(ids)} {args.model} servos ({span}) on {link} -> {emulator.port}{extra}", flush=True)
        while not stop.wait(0.2):
            if watch.parent_gone():
                break
    finally:
        if control is not None:
            control.close()
        emulator.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
