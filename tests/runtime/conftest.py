"""Fixtures for daemon tests: daemons on the sample head with its in-process emulators, on free loopback ports."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"


def daemon_overrides(tmp: Path, **extra: Any) -> dict[str, Any]:
    """Free ports on loopback and a private recording directory."""
    return {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
            "runtime.record_dir": str(tmp / "recordings"), **extra}


@pytest.fixture
def make_daemon(tmp_path: Path) -> Iterator[Callable[..., Any]]:
    """Start daemons on the sample head (overrides as keyword ``table__key=value``); all stopped afterwards."""
    from models.headspec import load_head
    from runtime.daemon import Daemon

    made: list[Daemon] = []

    def make(head_path: Path = SAMPLE, target_solvers: tuple = (), **extra: Any) -> Daemon:
        overrides = daemon_overrides(tmp_path, **{k.replace("__", "."): v for k, v in extra.items()})
        daemon = Daemon(load_head(head_path), overrides, target_solvers=target_solvers)
        made.append(daemon)
        daemon.start()
        return daemon

    yield make
    for daemon in made:
        daemon.stop()


@pytest.fixture(scope="module")
def shared_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One daemon for a whole test module (tests leave it inactive and fault-free)."""
    from models.headspec import load_head
    from runtime.daemon import Daemon

    daemon = Daemon(load_head(SAMPLE), daemon_overrides(tmp_path_factory.mktemp("daemon")))
    daemon.start()
    try:
        yield daemon
    finally:
        daemon.stop()


def enable_retrying(client: Any, tries: int = 3) -> None:
    """Enable the head; an emulator starved of CPU on a loaded host can miss a heartbeat or a reply window on the
    way up (a fault), so reset and try again. For tests whose subject comes after the enable."""
    from models.client import DaemonError

    for attempt in range(tries):
        try:
            client.call("enable", timeout=30)
            return
        except DaemonError:
            if attempt == tries - 1:
                raise
            time.sleep(1.0)
            client.request("reset", timeout=30)
