"""``likeness daemon``: run the realtime daemon of a head until SIGINT/SIGTERM (SIGUSR1 latches the e-stop)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from runtime.cli._client import SAMPLE_HEAD

if TYPE_CHECKING:
    from models.headspec import HeadSpec
    from runtime.daemon import Daemon


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The head, its inputs and the settings the command line overrides."""
    p = parser
    p.add_argument("--config", type=Path, default=SAMPLE_HEAD, help="head spec TOML (default: the sample head)")
    p.add_argument("--rate", type=float, default=None, help="loop rate in Hz (overrides [runtime] rate_hz)")
    p.add_argument("--command", default=None, help="command endpoint (overrides [api] command)")
    p.add_argument("--telemetry", default=None, help="telemetry endpoint (overrides [api] telemetry)")
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument("--enable", action="store_true", help="enable torque right after start-up")
    p.add_argument("--inputs", type=Path, default=None, metavar="FRAGMENT.toml",
                   help="add the show-control inputs of a file of [inputs.*] tables (docs/show_control.md)")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override one daemon setting, value in TOML syntax (repeatable)")


def overrides_from_args(args: argparse.Namespace) -> dict[str, object]:
    """Daemon setting overrides from --rate/--command/--telemetry/--no-realtime/--enable/--set."""
    import tomllib

    from models.errors import UsageError

    out: dict[str, object] = {}
    for item in args.set:
        key, sep, text = item.partition("=")
        if not sep:
            raise UsageError(f"--set {item!r}: expected TABLE.KEY=VALUE")
        try:
            out[key.strip()] = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = text
    if args.rate is not None:
        out["runtime.rate_hz"] = args.rate
    if args.command:
        out["api.command"] = args.command
    if args.telemetry:
        out["api.telemetry"] = args.telemetry
    if args.no_realtime:
        out["runtime.realtime"] = False
    if args.enable:
        out["runtime.auto_enable"] = True
    return out


def run(args: argparse.Namespace) -> int:
    """Start the daemon and serve until SIGINT/SIGTERM; SIGUSR1 latches the e-stop."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="likeness-head-", ignore_cleanup_errors=True) as tmp:
        daemon, head = _start(args, Path(tmp))
        _serve(daemon, head)
    print("daemon stopped", flush=True)
    return 0


def _start(args: argparse.Namespace, tmp: Path) -> tuple[Daemon, HeadSpec]:
    """Load the head (with the --inputs tables merged into a copy under ``tmp``) and start its daemon."""
    from drivers.errors import BusError
    from models.errors import ConfigError
    from models.headspec import load_head
    from runtime.cli._client import start_error
    from runtime.daemon import Daemon, DaemonStartError

    try:
        config = args.config
        if args.inputs is not None:
            from runtime.inputs.headfile import head_with_inputs

            config = head_with_inputs(args.config, args.inputs, tmp / args.config.name)
        head = load_head(config)
        daemon = Daemon(head, overrides_from_args(args))
    except OSError as exc:  # a config or asset error: one line, non-zero exit
        raise ConfigError(str(exc)) from exc
    try:
        daemon.start()
    except (BusError, DaemonStartError, OSError) as exc:
        raise start_error(exc, "cannot start: ") from exc
    return daemon, head


def _serve(daemon: Daemon, head: HeadSpec) -> None:
    """Announce the daemon and wait for SIGINT/SIGTERM (SIGUSR1: e-stop), then stop it."""
    import signal
    import threading

    stop = threading.Event()

    def on_stop(signum: int, frame: object) -> None:
        stop.set()

    def on_estop(signum: int, frame: object) -> None:
        daemon.estop("signal SIGUSR1")

    old = {s: signal.signal(s, on_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    old[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, on_estop)
    try:
        print(f"ready: head {head.name!r} ({len(head.actuators)} actuators) at {daemon.cfg.runtime.rate_hz:g} Hz; "
              f"commands {daemon.command_endpoint}, telemetry {daemon.telemetry_endpoint}; {daemon.realtime_status}",
              flush=True)
        if daemon.inputs.any:
            with_inputs = daemon.call("hello").get("inputs", {})
            print("inputs: " + "; ".join(f"{k} {v}" for k, v in with_inputs.items()), flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        daemon.stop()
