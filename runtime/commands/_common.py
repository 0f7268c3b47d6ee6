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
    """A :class:`models.client.Client` from the parsed options; CliError on bad key files."""
    from likeness.cli import CliError
    from models.client import Client

    try:
        return Client(args.endpoint, timeout=args.timeout, client_key=args.client_key, server_key=args.server_key)
    except (OSError, ValueError) as exc:
        raise CliError(str(exc)) from exc


#: Exit status of a ``likeness`` command by kind of error, the one table from errors to exit codes (names resolved
#: lazily so that ``likeness --help`` imports nothing). A kind not listed takes its nearest listed base's status.
#: 2: the request, config or an asset is wrong; 3: hardware (a bus failed or the daemon could not start);
#: 4: no daemon answered; 5: refused in the head's present state (inactive, fault, e-stop); 70: a bug.
EXIT_STATUS: dict[str, int] = {
    "models.errors.SpecError": 2,
    "drivers.errors.ConfigError": 2,
    "models.errors.ConfigError": 2,
    "models.errors.BadRequest": 2,
    "models.errors.BadValue": 2,
    "models.errors.NotFound": 2,
    "models.errors.TooLarge": 2,
    "models.errors.HardwareError": 3,
    "models.errors.StartError": 3,
    "drivers.errors.BusError": 3,
    "models.client.DaemonTimeout": 4,
    "models.errors.BadState": 5,
    "models.errors.InternalError": 70,
}


def exit_status(exc: BaseException) -> int:
    """The exit status for ``exc`` from :data:`EXIT_STATUS` (2 for anything not listed)."""
    for cls in type(exc).__mro__:
        status = EXIT_STATUS.get(f"{cls.__module__}.{cls.__qualname__}")
        if status is not None:
            return status
    return 2


def cli_error(exc: BaseException, prefix: str = "") -> Exception:
    """The :class:`likeness.cli.CliError` to raise for ``exc``: its one-line message and exit status. A daemon's
    error reply counts as the typed error its code stands for."""
    from likeness.cli import CliError
    from models.client import DaemonError

    kind = exc.error if isinstance(exc, DaemonError) else exc
    return CliError(f"{prefix}{exc}", exit_status(kind))


def call(client: Any, op: str, **fields: Any) -> dict[str, Any]:
    """One request; daemon errors and timeouts become CliError with the exit status of their kind."""
    from models.client import DaemonError, DaemonTimeout

    try:
        return client.call(op, **fields)
    except (DaemonError, DaemonTimeout) as exc:
        raise cli_error(exc) from exc
