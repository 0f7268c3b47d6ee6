"""Refused input packets: counted by reason and logged, at most one line per reason every few seconds."""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger("runtime.inputs")


class Refusals:
    """Counts and logs the packets an input refuses, rate-limited per reason."""

    def __init__(self, source: str, interval_s: float = 5.0) -> None:
        self.source = source
        self.interval_s = interval_s
        self.counts: dict[str, int] = {}
        self._last: dict[str, float] = {}
        self._quiet: dict[str, int] = {}
        self._lock = threading.Lock()

    def refuse(self, reason: str, detail: str = "") -> None:
        """Count one refused packet; log it unless this reason was logged within the interval."""
        now = time.monotonic()
        with self._lock:
            self.counts[reason] = self.counts.get(reason, 0) + 1
            if now - self._last.get(reason, -1e9) < self.interval_s:
                self._quiet[reason] = self._quiet.get(reason, 0) + 1
                return
            quiet = self._quiet.pop(reason, 0)
            self._last[reason] = now
        more = f" ({quiet} more since the last such line)" if quiet else ""
        log.warning("%s input: refused: %s%s%s", self.source, reason, f": {detail}" if detail else "", more)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)
