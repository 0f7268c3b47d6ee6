"""The sources stage: what drives the head this cycle (a clip, the stream's jitter buffer, live values, a pose,
neutral, or nothing: hold), and the commands that choose it.

:class:`SourcesState` keeps the active mode and the source that asked for it (the last active source wins), the
timeline of clips, the stream buffer, the live values, the pose in hand and the watchdog's stage. :func:`sample`
gives this cycle's drive: a channel vector for the solve stage, or actuator targets directly.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from models import errors as E
from runtime.core import commands as C
from runtime.core.cycle import CycleOutputs
from runtime.core.events import Body, ClipFinished, ClipPlaying, DroppedFrames, Watchdog
from runtime.core.lifecycle import LifecycleState, require_active
from runtime.core.live import LiveValues
from runtime.core.params import CoreParams
from runtime.core.stream import StreamBuffer
from runtime.timeline import Timeline


class Mode(enum.Enum):
    """Which source drives the head."""

    HOLD = "hold"
    CLIP = "clip"
    STREAM = "stream"
    POSE = "pose"
    NEUTRAL = "neutral"
    LIVE = "live"  # values from a show-control input (OSC, sACN)


@dataclass
class SourcesState:
    """The active mode and source, and every source's own state (clips, stream, live values, pose)."""

    timeline: Timeline
    stream: StreamBuffer
    live: LiveValues  # latest values of the live input (OSC, sACN) in mode LIVE
    channel_values: np.ndarray  # scratch: this cycle's channel vector
    mode: Mode = Mode.HOLD
    source: str | None = None  # what drives the head: "api", "osc", "sacn", "timecode" (None: nothing)
    pose_target: np.ndarray | None = None
    pose_speed: float = 0.25
    watchdog_stage: str = ""
    clip_done_reported: bool = False
    clip_bytes: int = 0  # memory the loaded clips take

    @classmethod
    def initial(cls, params: CoreParams) -> SourcesState:
        """Nothing loaded, nothing driving."""
        rt = params.cfg.runtime
        n = params.channels.n
        return cls(timeline=Timeline(),
                   stream=StreamBuffer(n, rt.stream_delay_s, rt.stream_max_frames, rt.stream_max_ahead_s),
                   live=LiveValues(n), channel_values=np.full(n, np.nan), pose_speed=params.cfg.safety.safe_speed)


class Drive(NamedTuple):
    """This cycle's drive: ``values`` is a channel vector to solve (``solve``) or actuator targets (SI, NaN = hold);
    ``speed`` the fraction of the limits to move at."""

    values: np.ndarray
    solve: bool
    speed: float


def set_mode(src: SourcesState, mode: Mode) -> None:
    """Change the mode (a new mode starts with the watchdog clear)."""
    if mode is not src.mode:
        src.mode = mode
        src.watchdog_stage = ""


def stop_motion(src: SourcesState) -> None:
    """Every source stops: the head holds."""
    set_mode(src, Mode.HOLD)
    src.timeline.stop()
    src.stream.clear()
    src.live.clear()
    src.pose_target = None
    src.source = None


def take_over(src: SourcesState, mode: Mode, source: str) -> None:
    """``source`` becomes the one driving the head (the last active source wins): the others stop."""
    if mode is not Mode.CLIP:
        src.timeline.stop()
    if mode is not Mode.STREAM or src.mode is not Mode.STREAM:
        src.stream.clear()
    if mode is not Mode.LIVE or src.mode is not Mode.LIVE or src.live.source != source:
        src.live.clear(source if mode is Mode.LIVE else None)
    src.pose_target = None
    set_mode(src, mode)
    src.source = source


def hold_pose(src: SourcesState, target: np.ndarray, speed: float) -> None:
    """A pose takes over: move to ``target`` (SI, constrained) at ``speed``."""
    take_over(src, Mode.POSE, "api")
    src.pose_target = target
    src.pose_speed = speed


# ---------------------------------------------------------------------- the cycle's drive
def sample(src: SourcesState, params: CoreParams, neutral: np.ndarray, out: CycleOutputs, t: float) -> Drive:
    """This cycle's drive from the active source (``neutral``: the head's neutral pose, SI)."""
    n = len(params.names)
    mode = src.mode
    if mode is Mode.CLIP:
        return _clip(src, n, out, t)
    if mode is Mode.STREAM or mode is Mode.LIVE:
        return _buffered(src, params, neutral, n, out, t)
    if mode is Mode.POSE and src.pose_target is not None:
        return Drive(src.pose_target, False, src.pose_speed)
    if mode is Mode.NEUTRAL:
        return Drive(neutral.copy(), False, params.cfg.safety.safe_speed)
    return Drive(np.full(n, np.nan), False, 1.0)


def _clip(src: SourcesState, n: int, out: CycleOutputs, t: float) -> Drive:
    tl = src.timeline
    ct = tl.clip_time(t)
    if ct is None:
        return Drive(np.full(n, np.nan), False, 1.0)
    pb = tl.playback
    assert pb is not None
    values = src.channel_values
    values.fill(np.nan)
    pb.clip.sample_into(ct, values)
    if tl.finished(t) and not src.clip_done_reported:
        src.clip_done_reported = True
        out.emit(ClipFinished(t, pb.clip.name))
    return Drive(values, True, 1.0)


def _buffered(src: SourcesState, params: CoreParams, neutral: np.ndarray, n: int, out: CycleOutputs,
              t: float) -> Drive:
    """The stream buffer or the live values, behind the watchdog: silence holds, then eases to neutral."""
    sf = params.cfg.safety
    live = src.mode is Mode.LIVE
    buffer: LiveValues | StreamBuffer = src.live if live else src.stream
    age = buffer.starved_for(t)
    hold_s = sf.watchdog_hold_s
    if live and src.live.watchdog_s is not None:
        hold_s = src.live.watchdog_s  # the input's own loss time (sACN: E1.31 data loss)
    if age > hold_s + (sf.watchdog_neutral_s - sf.watchdog_hold_s):
        out.emit(Watchdog(t, "neutral", age, src.source))
        set_mode(src, Mode.NEUTRAL)
        buffer.clear()
        return Drive(neutral.copy(), False, sf.safe_speed)
    if age > hold_s:
        if src.watchdog_stage != "hold":
            src.watchdog_stage = "hold"
            out.emit(Watchdog(t, "hold", age, src.source))
        return Drive(np.full(n, np.nan), False, 1.0)
    src.watchdog_stage = ""
    if not buffer.evaluate(t, src.channel_values):
        return Drive(np.full(n, np.nan), False, 1.0)
    return Drive(src.channel_values, True, 1.0)


# ---------------------------------------------------------------------- commands
def on_load_clip(src: SourcesState, params: CoreParams, cmd: C.LoadClip) -> Body:
    """Load (or replace) a clip within the clip memory budget."""
    clip = cmd.clip
    old = src.timeline.clips.get(clip.name)
    budget = params.cfg.runtime.clip_memory_bytes
    used = src.clip_bytes - (old.nbytes if old is not None else 0)
    if used + clip.nbytes > budget:
        raise E.TooLarge(f"clip {clip.name!r} needs {clip.nbytes} bytes; {budget - used} of the "
                         f"{budget}-byte clip budget left (unload_clip first)")
    try:
        src.timeline.load(clip)
    except ValueError as exc:
        raise E.TooLarge(str(exc)) from None
    src.clip_bytes = used + clip.nbytes
    return {"clip": clip.name, "duration": clip.duration, "channels": list(clip.channel_names),
            "keys": cmd.key_count}


def on_unload_clip(src: SourcesState, cmd: C.UnloadClip) -> Body:
    """Unload a clip (the head holds if it was playing)."""
    tl = src.timeline
    clip = tl.clips.get(cmd.name)
    if clip is None:
        raise E.NotFound(f"no clip {cmd.name!r} loaded; loaded: {sorted(tl.clips)}")
    if tl.playback is not None and tl.playback.clip is clip:
        stop_motion(src)
    tl.unload(cmd.name)
    src.clip_bytes -= clip.nbytes
    return {"clip": cmd.name, "clips": sorted(tl.clips)}


def on_play(src: SourcesState, life: LifecycleState, out: CycleOutputs, t: float, cmd: C.Play) -> Body:
    """Play a loaded clip: the clip takes over."""
    require_active(life, "play")
    if cmd.name not in src.timeline.clips:
        raise E.NotFound(f"no clip {cmd.name!r} loaded; loaded: {sorted(src.timeline.clips)}")
    if cmd.at is not None and not t - 3600 <= cmd.at <= t + 3600:
        raise E.BadValue(f"field 'at' must lie within an hour of the daemon clock ({t:.3f})")
    take_over(src, Mode.CLIP, cmd.source)
    start = src.timeline.play(cmd.name, t, cmd.at, cmd.offset, cmd.speed, cmd.loop)
    src.clip_done_reported = False
    out.emit(ClipPlaying(t, cmd.name, start))
    return {"clip": cmd.name, "start": start, "duration": src.timeline.clips[cmd.name].duration}


def on_pause(src: SourcesState, life: LifecycleState, t: float) -> Body:
    """Pause the playing clip."""
    require_active(life, "pause")
    src.timeline.pause(t)
    return {"timeline": src.timeline.describe(t)}


def on_resume(src: SourcesState, life: LifecycleState, t: float) -> Body:
    """Resume the paused clip (it takes over again)."""
    require_active(life, "resume")
    if src.timeline.playback is None:
        raise E.BadState("nothing to resume: no clip is playing")
    src.timeline.resume(t)
    if src.mode is not Mode.CLIP:
        take_over(src, Mode.CLIP, "api")
    return {"timeline": src.timeline.describe(t)}


def on_seek(src: SourcesState, life: LifecycleState, t: float, cmd: C.Seek) -> Body:
    """Move the playing clip to a clip time."""
    require_active(life, "seek")
    if src.timeline.playback is None:
        raise E.BadState("nothing to seek: no clip is playing")
    src.timeline.seek(t, cmd.time)
    return {"timeline": src.timeline.describe(t)}


def on_stream(src: SourcesState, life: LifecycleState, out: CycleOutputs, t: float, cmd: C.Stream) -> Body:
    """Frames into the jitter buffer: the stream takes over."""
    require_active(life, "stream")
    if src.mode is not Mode.STREAM:
        take_over(src, Mode.STREAM, "api")
    # Late means behind the play-out point by the time the frames reached the daemon (what the jitter buffer's
    # delay absorbs), not by the time this cycle took them; frames already played past stay late.
    arrival = t if cmd.received is None else min(t, cmd.received)
    counts = src.stream.push(arrival, cmd.times, cmd.channels, cmd.rows)
    if counts["late"]:
        out.emit(DroppedFrames(t, counts["late"], src.stream.late))
    return {"accepted": counts["ok"], "late": counts["late"], "ahead": counts["ahead"], "full": counts["full"],
            "buffered": src.stream.count, "t": t}


def on_live(src: SourcesState, life: LifecycleState, params: CoreParams, t: float, cmd: C.Live) -> Body:
    """Values from a live input: it takes over (the last active source wins) unless it only repeats itself."""
    require_active(life, f"{cmd.source} input")
    live = src.live
    if src.mode is not Mode.LIVE or live.source != cmd.source:
        if not cmd.takeover:
            return {"t": t, "ignored": True}
        take_over(src, Mode.LIVE, cmd.source)
    arrival = t if cmd.received is None else min(t, cmd.received)
    max_ahead = params.cfg.runtime.stream_max_ahead_s
    if cmd.at is not None and cmd.at > arrival + max_ahead:
        raise E.BadValue(f"time tag {cmd.at - arrival:.3f} s ahead; at most {max_ahead:g} s")
    if not live.push(arrival, cmd.channels, cmd.values, cmd.at, cmd.watchdog_s):
        raise E.TooLarge("too many timed updates waiting")
    return {"t": t}
