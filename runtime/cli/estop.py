"""``likeness estop``: latch a running daemon's e-stop (motion stops, torque off as configured)."""

from __future__ import annotations

import argparse

from runtime.cli._client import add_client_options, connect


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The client options and --reason."""
    add_client_options(parser)
    parser.add_argument("--reason", default="likeness estop", help="reason recorded with the e-stop")


def run(args: argparse.Namespace) -> int:
    """Send the e-stop."""
    with connect(args) as client:
        reply = client.call("estop", reason=args.reason)
    print(f"e-stop latched; lifecycle {reply['lifecycle']} (send 'likeness reset' to clear)")
    return 0
