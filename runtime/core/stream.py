"""The jitter buffer of streamed frames, on arrays: frames play ``delay`` seconds after their timestamp.

Each frame is a full-width channel vector (NaN for channels it does not carry). Evaluation interpolates linearly
between the two frames around the play-out time (a channel only one of them carries takes that frame's value), and
holds the last frame after it. A frame already behind the play-out point when it arrives is late (dropped, counted);
one further than ``max_ahead`` in the future is refused. The watchdog measures time since the last frame *received*.
"""

from __future__ import annotations

import numpy as np


class StreamBuffer:
    """Bounded, time-sorted ring of frames; no allocation per cycle."""

    def __init__(self, n_channels: int, delay: float, max_frames: int, max_ahead: float) -> None:
        self.delay = delay
        self.max_frames = max_frames
        self.max_ahead = max_ahead
        self.times = np.empty(max_frames)
        self.values = np.empty((max_frames, n_channels))
        self.count = 0  # frames held, sorted by time in rows [0, count)
        self.played_to = -np.inf
        self.last_arrival: float | None = None
        self.accepted = 0
        self.late = 0
        self.overflow = 0

    def clear(self) -> None:
        self.count = 0
        self.played_to = -np.inf
        self.last_arrival = None

    def push(self, now: float, times: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> dict[str, int]:
        """Insert frames (``times``, values ``rows[frames, len(idx)]`` for channels ``idx``); returns counts by
        outcome ("ok", "late", "ahead", "full")."""
        counts = {"ok": 0, "late": 0, "ahead": 0, "full": 0}
        for j in range(len(times)):
            t = float(times[j])
            if t <= self.played_to or t < now - self.delay:
                self.late += 1
                counts["late"] += 1
                continue
            if t > now + self.max_ahead:
                counts["ahead"] += 1
                continue
            c = self.count
            i = int(np.searchsorted(self.times[:c], t, side="right"))
            if i > 0 and self.times[i - 1] == t:  # same timestamp: the newer frame wins
                self.values[i - 1].fill(np.nan)
                self.values[i - 1, idx] = rows[j]
            else:
                if c >= self.max_frames:
                    self.overflow += 1
                    counts["full"] += 1
                    continue
                if i < c:
                    self.times[i + 1:c + 1] = self.times[i:c]
                    self.values[i + 1:c + 1] = self.values[i:c]
                self.times[i] = t
                self.values[i].fill(np.nan)
                self.values[i, idx] = rows[j]
                self.count = c + 1
            counts["ok"] += 1
            self.accepted += 1
            self.last_arrival = now
        return counts

    def evaluate(self, now: float, out: np.ndarray) -> bool:
        """Write the values at play-out time ``now - delay`` into ``out``; False before the first frame."""
        tp = now - self.delay
        c = self.count
        if c == 0 or tp < self.times[0]:
            return False
        i = int(np.searchsorted(self.times[:c], tp, side="right")) - 1
        if i > 0:  # frames before the one at or before the play-out time are no longer needed
            self.times[:c - i] = self.times[i:c]
            self.values[:c - i] = self.values[i:c]
            c = self.count = c - i
        self.played_to = max(self.played_to, tp)
        a = self.values[0]
        if c == 1:
            out[:] = a
            return True
        b = self.values[1]
        t0, t1 = self.times[0], self.times[1]
        u = (tp - t0) / (t1 - t0)
        np.copyto(out, a)
        out += u * (b - a)  # NaN where either lacks the channel ...
        only_b = np.isnan(a)
        out[only_b] = b[only_b]  # ... a channel only b carries takes b's value
        only_a = np.isnan(b) & ~only_b
        out[only_a] = a[only_a]
        return True

    def starved_for(self, now: float) -> float:
        """Seconds since the last frame was received (0 before any frame)."""
        return 0.0 if self.last_arrival is None else now - self.last_arrival

    def stats(self) -> dict[str, float | int]:
        return {"buffered": self.count, "accepted": self.accepted, "late": self.late, "overflow": self.overflow,
                "delay": self.delay}
