"""Show time: clip playback (play at a show time, loop, speed, pause, seek); streamed frames: runtime.core.stream.

Times are daemon-clock seconds (``time.monotonic()`` of the daemon's host); clients estimate their offset with the
``clock`` operation. Both classes are evaluated once per control cycle and never allocate much there.
"""

from __future__ import annotations

from dataclasses import dataclass

from models.clip import Clip, ClipError


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
