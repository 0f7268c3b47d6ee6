"""Timecode chase: which clip plays, and where, while following an external timecode; a pure state machine.

Timecode samples (seconds of timecode, the time they arrived) come from the timecode input; the core steps the
machine with its own time. States:

- ``stopped``: no timecode yet;
- ``locking``: samples arrive, not yet ``lock_samples`` in a row that agree with each other;
- ``locked``: following; each sample re-anchors the position, one further than ``jump_s`` from where the position
  was heading is a jump (the clip relocates);
- ``freewheel``: no sample for ``dropout_s``: the position runs on at speed 1 ...
- ``hold``: ... until ``freewheel_s`` after the last sample, then stays there; samples that agree again re-lock.

A full-frame message (a locate) relocates at once and parks (``hold``) until running timecode locks again.

Each chased clip has a chase offset: the timecode at which its clip time 0 plays. At timecode ``tc`` the clip with
the greatest offset at or before ``tc`` plays at clip time ``tc - offset`` (holding its last value past its end).
"""

from __future__ import annotations

from dataclasses import dataclass, field

STOPPED, LOCKING, LOCKED, FREEWHEEL, HOLD = "stopped", "locking", "locked", "freewheel", "hold"


@dataclass(frozen=True)
class ChaseParams:
    """Chase settings (``[inputs.timecode]``), seconds."""

    clips: tuple[tuple[str, float], ...] = ()  # (clip name, chase offset in timecode seconds)
    freewheel_s: float = 2.0  # run on this long after the last sample, then hold
    dropout_s: float = 0.15  # no sample this long: freewheeling (MTC gives one every two frames, ≤ 84 ms)
    jump_s: float = 0.25  # a sample this far from the running position relocates
    lock_samples: int = 3  # samples in a row that agree, to lock
    source: str = "mtc"  # what the clock status calls the source


@dataclass
class Chase:
    """The chase state; :meth:`feed` takes samples, :meth:`update` advances it in time."""

    params: ChaseParams = field(default_factory=ChaseParams)
    state: str = STOPPED
    anchor_tc: float = 0.0  # timecode seconds at daemon time anchor_t
    anchor_t: float = 0.0
    parked: float = 0.0  # timecode seconds where the chase holds (``hold``)
    last_sample: float | None = None  # daemon time of the last sample
    agree: int = 0  # samples in a row that agreed (while locking)
    fps: float = 0.0
    rate: str = ""  # "24", "25", "29.97df", "30"
    label: str = ""  # the last sample's timecode, as hh:mm:ss:ff (;ff for drop frame)
    jumps: int = 0
    samples: int = 0

    def _running(self, t: float) -> float:
        return self.anchor_tc + (t - self.anchor_t)

    def feed(self, tc: float, t: float, fps: float, rate: str, label: str, full: bool = False) -> str:
        """Take a sample (``full``: a full-frame locate); returns the event it causes: ``"lock"``, ``"jump"`` or
        ``""``."""
        self.samples += 1
        self.fps, self.rate, self.label = fps, rate, label
        previous = self.last_sample
        agrees = previous is not None and abs(tc - self._running(t)) <= self.params.jump_s
        self.last_sample = t
        if full:
            moved = previous is None or not agrees
            self.anchor_tc, self.anchor_t = tc, t
            self.parked = tc
            self.state, self.agree = HOLD, 0
            if moved:
                self.jumps += 1
                return "jump"
            return ""
        if self.state in (LOCKED, FREEWHEEL):
            self.anchor_tc, self.anchor_t = tc, t
            if agrees:
                was, self.state = self.state, LOCKED
                return "lock" if was == FREEWHEEL else ""
            self.state = LOCKED
            self.jumps += 1
            return "jump"
        # stopped, locking, hold: lock on lock_samples samples in a row that agree
        self.agree = self.agree + 1 if agrees else 1
        self.anchor_tc, self.anchor_t = tc, t
        if self.agree >= self.params.lock_samples:
            self.state, self.agree = LOCKED, 0
            return "lock"
        if self.state != HOLD:
            self.state = LOCKING
        return ""

    def update(self, t: float) -> str:
        """Advance to daemon time ``t``; returns ``"freewheel"`` or ``"hold"`` when the state changes so."""
        if self.last_sample is None:
            return ""
        age = t - self.last_sample
        if self.state == LOCKED and age > self.params.dropout_s:
            self.state = FREEWHEEL
            return FREEWHEEL
        if self.state == FREEWHEEL and age > self.params.freewheel_s:
            # park where freewheeling ended
            self.parked = self._running(self.last_sample + self.params.freewheel_s)
            self.state = HOLD
            return HOLD
        if self.state == LOCKING and age > self.params.freewheel_s:
            self.state, self.agree = STOPPED, 0
        return ""

    def position(self, t: float) -> float | None:
        """Timecode seconds at daemon time ``t`` (None before any lock or locate)."""
        if self.state in (LOCKED, FREEWHEEL):
            return self._running(t)
        if self.state == HOLD:
            return self.parked
        return None

    def clip_at(self, tc: float) -> tuple[str, float] | None:
        """(clip, clip time) that plays at timecode ``tc``; None before the first chased clip."""
        best: tuple[str, float] | None = None
        for name, offset in self.params.clips:
            if offset <= tc and (best is None or offset >= best[1]):
                best = (name, offset)
        return None if best is None else (best[0], tc - best[1])

    def describe(self, t: float) -> dict[str, object]:
        """The clock status: source, rate, lock state, the last timecode, where the chase is."""
        pos = self.position(t)
        sel = None if pos is None else self.clip_at(pos)
        return {"source": self.params.source, "rate": self.rate or None, "fps": self.fps or None, "state": self.state,
                "timecode": self.label or None, "seconds": pos,
                "age": None if self.last_sample is None else t - self.last_sample,
                "clip": None if sel is None else sel[0], "clip_time": None if sel is None else sel[1],
                "jumps": self.jumps, "samples": self.samples}
