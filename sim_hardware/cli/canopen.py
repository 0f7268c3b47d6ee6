"""``likeness sim canopen``: serve emulated CiA 402 drives to other processes over socketcand.

The drives and a socketcand-protocol server on loopback share one in-process bus (frames pass by
function call, see :mod:`sim_hardware.socketcand`), so a master in another process connects with
``can.Bus(interface="socketcand", host=HOST, port=PORT, channel="can0")`` (for the ``canopen402``
driver: options ``interface="socketcand", host, port, channel``). Prints one ready line, serves
until SIGINT or SIGTERM, then exits 0.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sim_hardware.cli._server import StopSignals


def parse_nodes(text: str) -> list[int]:
    """``"1-13"`` or ``"1,3,5-7"`` → sorted node ids (UsageError naming the bad part)."""
    from models.errors import UsageError

    ids: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if lo > hi:
                    raise ValueError
                ids.update(range(lo, hi + 1))
            else:
                ids.add(int(part))
        except ValueError:
            raise UsageError(f"--nodes: cannot parse {part!r} (use e.g. 1-13 or 1,3,5-7)") from None
    bad = sorted(n for n in ids if not 1 <= n <= 127)
    if not ids or bad:
        raise UsageError(f"--nodes: node ids must be 1..127, got {bad or text!r}")
    return sorted(ids)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The drives, the socketcand server and the emulation's settings."""
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--nodes", default="1-13", help="node ids, e.g. 1-13 or 1,3,5-7 (default 1-13)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=29536, help="TCP port, 0 for any free one (default 29536)")
    parser.add_argument("--channel", default="can0", help="socketcand channel name clients open (default can0)")
    parser.add_argument("--control", metavar="ENDPOINT", help="serve fault injection on this ZeroMQ endpoint")
    parser.add_argument("--eds-out", metavar="PATH", help="also write the drives' object dictionary as an EDS")
    parser.add_argument("--heartbeat-ms", type=int, default=0, help="heartbeat producer time at boot (0x1017)")
    parser.add_argument("--physics-hz", type=float, default=1000.0, help="motor model rate (default 1000)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the frame-fault random generator")
    parser.add_argument("--initial-positions", default="", metavar="ID=COUNTS,...",
                        help="start position of drives in encoder counts, e.g. 1=0,2=-512 (default 0)")
    parser.add_argument("--watch-parent", action="store_true",
                        help="exit when the process that started this one exits")


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM; returns 0 after a clean shutdown."""
    from sim_hardware.cli._server import StopSignals

    nodes, initial = _checked(args)
    with StopSignals(args.watch_parent) as signals:
        _serve(args, nodes, initial, signals)
    return 0


def _checked(args: argparse.Namespace) -> tuple[list[int], dict[int, float]]:
    """The node ids and start positions of the options (UsageError naming a bad one); writes the EDS if asked."""
    from models.errors import UsageError

    nodes = parse_nodes(args.nodes)
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port: must be 0..65535, got {args.port}")
    if not 0 <= args.heartbeat_ms <= 65535:
        raise UsageError(f"--heartbeat-ms: must be 0..65535, got {args.heartbeat_ms}")
    if args.physics_hz <= 0:
        raise UsageError(f"--physics-hz: must be positive, got {args.physics_hz}")

    from sim_hardware.canopen.od import write_eds
    from sim_hardware.cli._server import parse_counts

    if args.eds_out:
        try:
            path = write_eds(args.eds_out, nodes[0])
        except OSError as exc:
            raise UsageError(f"--eds-out: cannot write {args.eds_out}: {exc}") from exc
        print(f"wrote EDS of node {nodes[0]} to {path}", file=sys.stderr)

    try:
        initial = parse_counts(args.initial_positions)
    except ValueError as exc:
        raise UsageError(f"--initial-positions: {exc}") from None
    unknown = sorted(set(initial) - set(nodes))
    if unknown:
        raise UsageError(f"--initial-positions: node ids {unknown} are not among --nodes {args.nodes}")
    return nodes, initial


def _serve(args: argparse.Namespace, nodes: list[int], initial: dict[int, float], signals: StopSignals) -> None:
    """Run the drives, the socketcand server and the control endpoint until ``signals`` says stop."""
    from models.errors import UsageError
    from sim_hardware.canopen.network import DriveSet
    from sim_hardware.socketcand import SocketcandServer

    internal = f"likeness-sim-canopen-{os.getpid()}"
    drives = DriveSet(nodes, channel=internal, heartbeat_ms=args.heartbeat_ms, physics_hz=args.physics_hz,
                      seed=args.seed, initial_positions=initial)
    server = control = None
    try:
        try:
            server = SocketcandServer(on_frame=drives.deliver, host=args.host, port=args.port, channel=args.channel)
        except OSError as exc:
            raise UsageError(f"--port: cannot listen on {args.host}:{args.port}: {exc}") from exc
        drives.start(transport=server.publish)
        server.start()
        if args.control:
            from models.emulator_control import ControlServer

            try:
                control = ControlServer(args.control, drives.handle_control)
            except Exception as exc:
                raise UsageError(f"--control: cannot bind {args.control}: {exc}") from exc
        extra = f", control {control.endpoint}" if control else ""
        print(
            f"ready: {len(nodes)} CiA 402 drives (nodes {args.nodes}) on socketcand "
            f"{server.host}:{server.port} channel {args.channel}{extra}",
            flush=True,
        )
        signals.wait()
    finally:
        if control is not None:
            control.close()
        if server is not None:
            server.stop()
        drives.stop()
