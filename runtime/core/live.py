"""Live values: the latest value of every channel a show-control input (OSC, sACN) has set, on arrays.

Unlike the stream's jitter buffer, a live input sends values, not timestamped frames: each update sets some channels
and the others keep their last value. An update may carry a time (an OSC bundle's timetag): it is held until then
and applied whole, so every channel of a bundle changes in the same cycle. The watchdog measures time since the last
update *received*, as for the stream.
"""

from __future__ import annotations

import numpy as np

#: Timed updates waiting for their time, at most.
MAX_PENDING = 256


class LiveValues:
    """One channel vector of latest values (NaN: never set since the source became active) and timed updates."""

    def __init__(self, n_channels: int) -> None:
        self.values = np.full(n_channels, np.nan)
        self.pending: list[tuple[float, int, np.ndarray, np.ndarray]] = []  # (at, seq, channels, values), by time
        self.last_arrival: float | None = None
        self.source: str | None = None
        self.watchdog_s: float | None = None  # the source's own silence before the watchdog holds
        self.updates = 0
        self.refused = 0
        self._seq = 0

    def clear(self, source: str | None = None) -> None:
        """Forget every value and pending update; ``source`` becomes the live source."""
        self.values.fill(np.nan)
        self.pending.clear()
        self.last_arrival = None
        self.source = source
        self.watchdog_s = None

    def push(self, now: float, channels: np.ndarray, values: np.ndarray, at: float | None = None,
             watchdog_s: float | None = None) -> bool:
        """Set ``channels`` to ``values`` now, or at daemon time ``at`` when that is later; False when too many
        timed updates are already waiting (the update is refused)."""
        self.last_arrival = now
        self.watchdog_s = watchdog_s
        if at is None or at <= now:
            self.values[channels] = values
            self.updates += 1
            return True
        if len(self.pending) >= MAX_PENDING:
            self.refused += 1
            return False
        self._seq += 1
        self.pending.append((at, self._seq, channels, values))
        self.pending.sort(key=lambda p: (p[0], p[1]))
        return True

    def evaluate(self, now: float, out: np.ndarray) -> bool:
        """Apply the updates that are due and write the values into ``out``; False while nothing was ever set."""
        while self.pending and self.pending[0][0] <= now:
            _, _, channels, values = self.pending.pop(0)
            self.values[channels] = values
            self.updates += 1
        np.copyto(out, self.values)
        return bool(np.isfinite(self.values).any())

    def starved_for(self, now: float) -> float:
        """Seconds since the last update was received (0 before any)."""
        return 0.0 if self.last_arrival is None else now - self.last_arrival

    def stats(self) -> dict[str, object]:
        return {"source": self.source, "updates": self.updates, "pending": len(self.pending),
                "refused": self.refused}
