"""What the runtime's commands share (standard library only): default endpoints, the sample head, the daemon
client's options and connecting with them."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from models.client import Client

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


def connect(args: argparse.Namespace) -> Client:
    """A :class:`models.client.Client` from the parsed options; :class:`models.errors.UsageError` on bad key files.
    Its requests raise ``DaemonError``/``DaemonTimeout``, which ``likeness`` reports with their exit status."""
    from models.client import Client
    from models.errors import UsageError

    try:
        return Client(args.endpoint, timeout=args.timeout, client_key=args.client_key, server_key=args.server_key)
    except (OSError, ValueError) as exc:
        raise UsageError(str(exc)) from exc


def lifecycle_request(args: argparse.Namespace, op: str) -> int:
    """Send one lifecycle request (``enable``, ``disable``, ``reset``) and print the head's lifecycle after it."""
    with connect(args) as client:
        reply = client.call(op)
    print(f"{op}: lifecycle {reply['lifecycle']}")
    return 0


def start_error(exc: BaseException, prefix: str) -> Exception:
    """The error to report when the daemon could not start: ``exc``'s message after ``prefix``, as a config error
    when a head spec or bus config was wrong and a start error otherwise (bus, API server, loop, operating system)."""
    from drivers.errors import ConfigError as BusConfigError
    from models.errors import ConfigError, SpecError, StartError

    kind = ConfigError if isinstance(exc, (SpecError, BusConfigError)) else StartError
    return kind(f"{prefix}{exc}")
