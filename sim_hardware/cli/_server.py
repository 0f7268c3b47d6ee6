"""What the ``likeness sim`` device servers share (standard library only): per-device start positions and parent
supervision."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any


def parse_counts(text: str) -> dict[int, float]:
    """``"1=120,2=-4096.5"`` → ``{1: 120.0, 2: -4096.5}`` (ValueError naming the bad part)."""
    out: dict[int, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        try:
            if not sep:
                raise ValueError
            out[int(key)] = float(value)
        except ValueError:
            raise ValueError(f"cannot parse {part!r} (use ID=COUNTS, e.g. 1=120,2=-4096)") from None
    return out


class ParentWatch:
    """Tells whether the process that started this one is gone (re-parented), so a server can exit with it."""

    def __init__(self, enabled: bool) -> None:
        self._parent = os.getppid() if enabled else None

    def parent_gone(self) -> bool:
        """True once the starting process has exited (always False when not watching)."""
        return self._parent is not None and os.getppid() != self._parent


class StopSignals:
    """Inside its ``with`` block SIGINT and SIGTERM ask the server to stop (the previous handlers come back on exit);
    :meth:`wait` returns once asked, or once the starting process is gone when ``watch_parent``."""

    def __init__(self, watch_parent: bool) -> None:
        self._watch = ParentWatch(watch_parent)
        self._stop = threading.Event()
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        self._previous = {sig: signal.signal(sig, lambda *_: self._stop.set())
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def wait(self) -> None:
        """Block until SIGINT/SIGTERM, or until the starting process exits (when watched)."""
        while not self._stop.wait(0.2):
            if self._watch.parent_gone():
                break
