"""The chase stage: timecode samples feed the chase (:mod:`runtime.core.chase`, a pure state machine), and while the
timecode drives the head, the timeline plays the chased clip at the chased clip time.

The chase's state is the :class:`~runtime.core.chase.Chase` itself; this stage reads the lifecycle and places the
clip on the sources' timeline.
"""

from __future__ import annotations

from models import errors as E
from runtime.core import commands as C
from runtime.core.chase import HOLD, Chase
from runtime.core.cycle import CycleOutputs
from runtime.core.events import Body, ClipPlaying, TimecodeChanged
from runtime.core.lifecycle import Lifecycle, LifecycleState
from runtime.core.sources import Mode, SourcesState, take_over


def on_timecode(chase: Chase | None, src: SourcesState, life: LifecycleState, out: CycleOutputs, t: float,
                cmd: C.Timecode) -> Body:
    """A timecode sample: the chase follows it; a lock or a jump hands the head to the timecode (when active)."""
    if chase is None:
        raise E.BadState("no timecode input is configured ([inputs.timecode])")
    change = chase.feed(cmd.seconds, min(t, cmd.received), cmd.fps, cmd.rate, cmd.label, cmd.full)
    if change:
        out.emit(TimecodeChanged(t, chase.state, change, chase.label, chase.rate))
        if life.commanding:
            take_over(src, Mode.CLIP, "timecode")
            _place(chase, src, out, t)
    return {"state": chase.state}


def follow(chase: Chase, src: SourcesState, life: LifecycleState, out: CycleOutputs, t: float) -> None:
    """Advance the chase (dropout → freewheel → hold) and, while the timecode drives, place the clip."""
    change = chase.update(t)
    if change:
        out.emit(TimecodeChanged(t, chase.state, change, chase.label, chase.rate))
    if src.source == "timecode" and src.mode is Mode.CLIP and life.lifecycle is Lifecycle.ACTIVE:
        _place(chase, src, out, t)


def _place(chase: Chase, src: SourcesState, out: CycleOutputs, t: float) -> None:
    """The timeline plays the chased clip at the chased clip time (paused while the chase holds)."""
    tl = src.timeline
    tc = chase.position(t)
    sel = None if tc is None else chase.clip_at(tc)
    if sel is None or sel[0] not in tl.clips:
        tl.stop()  # before the first chased clip (or it is not loaded): hold
        return
    name, ct = sel
    pb = tl.playback
    if pb is None or pb.clip.name != name:
        tl.play(name, t, None, ct, 1.0, False)
        src.clip_done_reported = False
        out.emit(ClipPlaying(t, name, t - ct, source="timecode"))
        pb = tl.playback
        assert pb is not None
    if ct < pb.clip.duration:
        src.clip_done_reported = False
    pb.offset, pb.start, pb.speed = ct, t, 1.0
    pb.paused_at = ct if chase.state == HOLD else None
