"""What the core reports: the telemetry snapshot every telemetry period, and the fuller ``status`` reply.

Raw values (SI arrays) in maps; the API server formats them (units, link poses).
"""

from __future__ import annotations

import numpy as np

from runtime.core.events import Body
from runtime.core.params import CoreParams
from runtime.core.sources import Mode
from runtime.core.state import CoreState
from runtime.core.watch import feedback_ages


def snapshot(state: CoreState, params: CoreParams, t: float) -> Body:
    """The telemetry snapshot at ``t``."""
    fb, src = state.feedback, state.sources
    body: Body = {
        "t": t, "lifecycle": state.life.lifecycle.value, "mode": src.mode.value,
        "commanded_si": state.shaper.q.copy(), "measured_si": fb.measured.copy(),
        "buses": dict(fb.states), "connected": dict(fb.connected),
        "connection": {name: info.as_dict() for name, info in fb.connections.items()},
        "guard": {"verdict": state.guard.verdict, "refused": state.guard.refused},
        "feedback_age": dict(zip(fb.reported, feedback_ages(fb.reported, t, -np.inf), strict=True)),
        "following_error_si": state.watch.peak_error.copy(),
    }
    pb = src.timeline.playback
    if pb is not None:
        body["clip"] = {"name": pb.clip.name, "time": src.timeline.clip_time(t), "duration": pb.clip.duration}
    if src.mode is Mode.STREAM:
        body["stream"] = src.stream.stats()
    body["source"] = src.source
    if src.mode is Mode.LIVE:
        body["live"] = src.live.stats()
    if state.chase is not None:
        body["clock"] = state.chase.describe(t)
    if state.solve.extra:
        body["extra"] = dict(state.solve.extra)
    return body


def status(state: CoreState, params: CoreParams, t: float) -> Body:
    """The ``status`` reply: the snapshot plus e-stop, fault, motion, timeline, stream, recording and clip memory;
    for a pose, whether it is reached or settled where the safety stage let it go."""
    src, life, rec = state.sources, state.life, state.recorder
    moving = bool(np.any(np.abs(state.shaper.v) > 1e-4))
    body = snapshot(state, params, t)
    body.update({
        "estop": life.estop_reason, "fault": None if life.fault is None else life.fault.info(),
        "moving": moving, "timeline": src.timeline.describe(t), "stream": src.stream.stats(),
        "recording": None if rec.name is None else {"name": rec.name, "samples": rec.total},
        "clip_bytes": src.clip_bytes,
    })
    if src.mode is Mode.POSE and src.pose_target is not None:
        err = np.abs(src.pose_target - state.shaper.q)
        reached = bool(np.all(err < 1e-6) and not moving)
        body["pose_reached"] = reached
        # stopped where the safety stage let it go: at the target, or short of it where the strain guard limited it
        body["pose_settled"] = bool(not moving and (reached or state.guard.verdict != "ok"))
    return body
