"""Shared command-line options of the daemon's client commands (standard library only)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

DEFAULT_COMMAND = "tcp://127.0.0.1:5555"
DEFAULT_TELEMETRY = "tcp://127.0.0.1:5556"
SAMPLE_HEAD = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def add_client_options(parser: argparse.ArgumentParser, telemetry: bool = False) -> None:
    """--endpoint, --timeout and the CURVE key options of a client command."""
    parser.add_argument("--endpoint", default=DEFAULT_COMMAND,
                        help=f"daemon command socket (default {DEFAULT_COMMAND})")
    if telemetry:
        parser.add_argument("--telemetry", default=None,
                            help="daemon telemetry socket (default: the one the daemon announces in hello)")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for a reply (default 3)")
    parser.add_argument("--client-key", type=Path, default=None,
                        help="CURVE: this client's secret key file (from 'likeness keys')")
    parser.add_argument("--server-key", type=Path, default=None, help="CURVE: the daemon's public key file")


def connect(args: argparse.Namespace) -> Any:
    """A :class:`runtime.client.Client` from the parsed options; CliError on bad key files."""
    from likeness.cli import CliError
    from runtime.client import Client

    try:
        return Client(args.endpoint, timeout=args.timeout, client_key=args.client_key, server_key=args.server_key)
    except (OSError, ValueError) as exc:
        raise CliError(str(exc)) from exc


def call(client: Any, op: str, **fields: Any) -> dict[str, Any]:
    """One request; daemon errors and timeouts become CliError."""
    from likeness.cli import CliError
    from runtime.client import DaemonError, DaemonTimeout

    try:
        return client.call(op, **fields)
    except (DaemonError, DaemonTimeout) as exc:
        raise CliError(str(exc)) from exc
