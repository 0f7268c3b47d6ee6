"""The jitter buffer of streamed frames, on arrays: frames play ``delay`` seconds after their timestamp.

Each frame is a full-width channel vector (NaN for channels it does not carry). Evaluation interpolates linearly
between the two frames around the play-out time (a channel only one of them carries takes that frame's value), and
holds the last frame after it. A frame already behind the play-out point when it arrives is late (dropped, counted);
one further than ``max_ahead`` in the future is refused. The watchdog measures time since the last frame *received*,
so frames far in the future never postpone it.

Frames live in rows ``[head, end)`` of preallocated arrays, sorted by time: playing out advances ``head``, in-order
batches are appended with one copy, and rows are compacted only when the end of the arrays is reached.
"""

from __future__ import annotations

import numpy as np


class StreamBuffer:
    """Bounded, time-sorted frames; no allocation per cycle."""

    def __init__(self, n_channels: int, delay: float, max_frames: int, max_ahead: float) -> None:
        self.delay = delay
        self.max_frames = max_frames
        self.max_ahead = max_ahead
        self.times = np.empty(max_frames)
        self.values = np.empty((max_frames, n_channels))
        self.head = 0
        self.end = 0
        self.played_to = -np.inf
        self.last_arrival: float | None = None
        self.accepted = 0
        self.late = 0
        self.overflow = 0

    @property
    def count(self) -> int:
        return self.end - self.head

    def clear(self) -> None:
        self.head = self.end = 0
        self.played_to = -np.inf
        self.last_arrival = None

    def _room(self, k: int) -> int:
        """Make room for up to ``k`` rows at the end (compacting if needed); returns how many fit."""
        if self.end + k > self.max_frames and self.head > 0:
            c = self.count
            self.times[:c] = self.times[self.head:self.end]
            self.values[:c] = self.values[self.head:self.end]
            self.head, self.end = 0, c
        return min(k, self.max_frames - self.end)

    def push(self, now: float, times: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> dict[str, int]:
        """Insert frames (``times``, values ``rows[frames, len(idx)]`` for channels ``idx``); returns counts by
        outcome ("ok", "late", "ahead", "full"). Frames in time order after the buffered ones (the usual case) are
        appended with one array copy; others are merged one by one."""
        times = np.asarray(times, dtype=float)
        late = (times <= self.played_to) | (times < now - self.delay)
        ahead = ~late & (times > now + self.max_ahead)
        keep = ~late & ~ahead
        counts = {"ok": 0, "late": int(late.sum()), "ahead": int(ahead.sum()), "full": 0}
        self.late += counts["late"]
        t_in = times[keep]
        if t_in.size:
            r_in = rows[keep]
            if (self.count == 0 or t_in[0] > self.times[self.end - 1]) and bool(np.all(np.diff(t_in) > 0)):
                k = self._room(len(t_in))
                e = self.end
                self.times[e:e + k] = t_in[:k]
                block = self.values[e:e + k]
                block.fill(np.nan)
                block[:, idx] = r_in[:k]
                self.end = e + k
                counts["ok"] = k
                counts["full"] = len(t_in) - k
            else:
                for t, row in zip(t_in.tolist(), r_in, strict=True):
                    counts[self._insert(t, idx, row)] += 1
        self.overflow += counts["full"]
        self.accepted += counts["ok"]
        if counts["ok"]:
            self.last_arrival = now
        return counts

    def _insert(self, t: float, idx: np.ndarray, row: np.ndarray) -> str:
        h = self.head
        i = h + int(np.searchsorted(self.times[h:self.end], t, side="right"))
        if i > h and self.times[i - 1] == t:  # same timestamp: the newer frame wins
            self.values[i - 1].fill(np.nan)
            self.values[i - 1, idx] = row
            return "ok"
        if self._room(1) < 1:
            return "full"
        i -= h - self.head  # compaction may have moved the rows
        e = self.end
        if i < e:
            self.times[i + 1:e + 1] = self.times[i:e]
            self.values[i + 1:e + 1] = self.values[i:e]
        self.times[i] = t
        self.values[i].fill(np.nan)
        self.values[i, idx] = row
        self.end = e + 1
        return "ok"

    def evaluate(self, now: float, out: np.ndarray) -> bool:
        """Write the values at play-out time ``now - delay`` into ``out``; False before the first frame."""
        tp = now - self.delay
        h, e = self.head, self.end
        if e == h or tp < self.times[h]:
            return False
        # frames before the one at or before the play-out time are no longer needed
        i = h + int(np.searchsorted(self.times[h:e], tp, side="right")) - 1
        self.head = h = i
        self.played_to = max(self.played_to, tp)
        a = self.values[h]
        if e - h == 1:
            out[:] = a
            return True
        b = self.values[h + 1]
        t0, t1 = self.times[h], self.times[h + 1]
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
