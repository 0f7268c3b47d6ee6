"""Show time: clip playback (play at a show time, loop, speed, pause, seek) and the jitter buffer of streamed frames.

Times are daemon-clock seconds (``time.monotonic()`` of the daemon's host); clients estimate their offset with the
``clock`` operation. Both classes are evaluated once per control cycle and never allocate much there.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass

from runtime.curves import Clip, ClipError


@dataclass
class Playback:
    """The clip being played: clip time = offset + (now - start) * speed while running."""

    clip: Clip
    start: float  # daemon time at which clip time ``offset`` plays
    offset: float
    speed: float
    loop: bool
    paused_at: float | None = None  # clip time held while paused


class Timeline:
    """Clips by name and the one playing; :meth:`evaluate` gives channel values at a show time."""

    MAX_CLIPS = 64

    def __init__(self) -> None:
        self.clips: dict[str, Clip] = {}
        self.playback: Playback | None = None

    def load(self, clip: Clip) -> None:
        """Add or replace a clip (a playing clip of the same name keeps playing its old curves until ``play``)."""
        if clip.name not in self.clips and len(self.clips) >= self.MAX_CLIPS:
            raise ClipError(f"at most {self.MAX_CLIPS} clips may be loaded; unload one first")
        self.clips[clip.name] = clip

    def unload(self, name: str) -> None:
        self.clips.pop(name, None)

    def play(self, name: str, now: float, at: float | None, offset: float, speed: float, loop: bool) -> float:
        """Start ``name`` so that clip time ``offset`` plays at daemon time ``at`` (now if None); returns ``at``."""
        clip = self.clips[name]
        start = now if at is None else at
        self.playback = Playback(clip, start, offset, speed, loop)
        return start

    def clip_time(self, now: float) -> float | None:
        """Clip time at daemon time ``now`` (None when nothing is playing or it has not started yet)."""
        pb = self.playback
        if pb is None:
            return None
        if pb.paused_at is not None:
            return pb.paused_at
        if now < pb.start:
            return None
        t = pb.offset + (now - pb.start) * pb.speed
        duration = pb.clip.duration
        if pb.loop and duration > 0:
            t = t % duration
        return t

    def finished(self, now: float) -> bool:
        pb = self.playback
        if pb is None or pb.loop or pb.paused_at is not None:
            return False
        t = self.clip_time(now)
        return t is not None and t >= pb.clip.duration

    def evaluate(self, now: float) -> dict[str, float] | None:
        """Channel values at daemon time ``now``, or None when no clip is playing yet."""
        t = self.clip_time(now)
        if t is None:
            return None
        return self.playback.clip.sample(t)  # type: ignore[union-attr]

    def pause(self, now: float) -> None:
        pb = self.playback
        if pb is not None and pb.paused_at is None:
            pb.paused_at = self.clip_time(now) if now >= pb.start else pb.offset

    def resume(self, now: float) -> None:
        pb = self.playback
        if pb is not None and pb.paused_at is not None:
            pb.offset, pb.start, pb.paused_at = pb.paused_at, now, None

    def seek(self, now: float, t: float) -> None:
        pb = self.playback
        if pb is None:
            return
        if pb.paused_at is not None:
            pb.paused_at = t
        else:
            pb.offset, pb.start = t, now

    def stop(self) -> None:
        self.playback = None

    def describe(self, now: float) -> dict[str, object]:
        """Playback state for status replies."""
        pb = self.playback
        if pb is None:
            return {"clip": None, "clips": sorted(self.clips)}
        return {
            "clip": pb.clip.name, "time": self.clip_time(now), "duration": pb.clip.duration, "speed": pb.speed,
            "loop": pb.loop, "paused": pb.paused_at is not None, "start": pb.start,
            "finished": self.finished(now), "clips": sorted(self.clips),
        }


class JitterBuffer:
    """Timestamped frames played ``delay`` seconds after their timestamp, interpolated linearly.

    A frame whose time is already behind the play-out point when it arrives is late: dropped and counted. Frames are
    kept sorted, so moderate reordering in transit is absorbed by the delay.
    """

    def __init__(self, delay: float, max_frames: int, max_ahead: float) -> None:
        self.delay = delay
        self.max_frames = max_frames
        self.max_ahead = max_ahead
        self._times: list[float] = []
        self._values: list[Mapping[str, float]] = []
        self._played_to = float("-inf")  # stream time last played out
        self.last_arrival: float | None = None
        self.last_time = float("-inf")  # newest frame timestamp pushed
        self.accepted = 0
        self.late = 0
        self.overflow = 0

    def clear(self) -> None:
        self._times.clear()
        self._values.clear()
        self._played_to = float("-inf")
        self.last_arrival = None
        self.last_time = float("-inf")

    def __len__(self) -> int:
        return len(self._times)

    def push(self, now: float, t: float, values: Mapping[str, float]) -> str:
        """Insert one frame; returns "ok", "late", "ahead" or "full"."""
        if t <= self._played_to or t < now - self.delay:
            self.late += 1
            return "late"
        if t > now + self.max_ahead:
            return "ahead"
        if len(self._times) >= self.max_frames:
            self.overflow += 1
            return "full"
        i = bisect.bisect_right(self._times, t)
        if i > 0 and self._times[i - 1] == t:
            self._values[i - 1] = values  # same timestamp: the newer frame wins
        else:
            self._times.insert(i, t)
            self._values.insert(i, values)
        self.accepted += 1
        self.last_arrival = now
        self.last_time = max(self.last_time, t)
        return "ok"

    def evaluate(self, now: float) -> dict[str, float] | None:
        """Values at play-out time ``now - delay`` (held after the last frame), or None before the first frame."""
        tp = now - self.delay
        times = self._times
        if not times or tp < times[0]:
            return None
        i = bisect.bisect_right(times, tp) - 1
        # Drop frames that can no longer be needed (keep the one at or before the play-out time).
        if i > 0:
            del times[:i]
            del self._values[:i]
            i = 0
        self._played_to = max(self._played_to, tp)
        a = self._values[0]
        if len(times) == 1:
            return dict(a)
        t0, t1 = times[0], times[1]
        b = self._values[1]
        u = (tp - t0) / (t1 - t0)
        out = dict(a)
        for ch, vb in b.items():
            va = a.get(ch)
            out[ch] = vb if va is None else va + u * (vb - va)
        return out

    def starved_for(self, now: float) -> float:
        """How long the play-out has had no fresh data: since the later of the last arrival and the moment the
        last buffered frame played out (0 before any frame)."""
        if self.last_arrival is None:
            return 0.0
        return now - max(self.last_arrival, self.last_time + self.delay)

    def stats(self) -> dict[str, int | float]:
        return {"buffered": len(self._times), "accepted": self.accepted, "late": self.late,
                "overflow": self.overflow, "delay": self.delay}
