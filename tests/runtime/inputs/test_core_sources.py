"""The core with live (OSC, sACN) and timecode sources, stepped directly on ideal buses (no sockets, no sleeps):
the last active source wins, live values pass the watchdog and the lifecycle, and the chase places the clip."""

from __future__ import annotations

import numpy as np
import pytest

from models.clip import clip_from_dict
from runtime.core import commands as C
from runtime.core.chase import ChaseParams
from runtime.core.clips import bind_clip
from runtime.core.params import CoreParams
from runtime.core.sources import Mode
from runtime.core.state import CoreState
from tests.runtime.test_core import HEAD, Rig

RAMP = {"name": "ramp", "channels": {"jaw": {"interp": "linear", "keys": [[0, 0], [20, 20]]}}}


class ChaseRig(Rig):
    def __init__(self, **chase: object) -> None:
        super().__init__()
        self.params = CoreParams.build(HEAD, self.cfg, self.channels, [(b, [a.name for a in HEAD.actuators_on(b)])
                                                                         for b in HEAD.buses],
                                         chase=ChaseParams(**chase))
        self.state = CoreState.initial(HEAD, self.params)


def _deg(rig: Rig, name: str) -> float:
    return float(np.degrees(rig.state.shaper.q[HEAD.actuator_names.index(name)]))


def _live(rig: Rig, source: str, **values: float) -> C.Live:
    idx = rig.channels.indices(list(values))
    return C.Live(0, source, idx, np.array(list(values.values())), None, rig.t)


def test_live_values_drive_until_another_source_takes_over() -> None:
    r = Rig()
    out = r.cycle(_live(r, "osc", jaw=5.0))
    assert out.replies[0][1]["error"]["code"] == "bad_state"  # inactive: refused
    r.call(C.Enable)
    for _ in range(100):
        r.cycle(_live(r, "osc", jaw=5.0))
    assert r.state.mode is Mode.LIVE and r.state.source == "osc"
    assert _deg(r, "jaw") == pytest.approx(5.0, abs=1e-6)
    # sACN repeats do not take over; a change does
    r.cycle(C.Live(0, "sacn", r.channels.indices(["jaw"]), np.array([9.0]), None, r.t, takeover=False))
    assert r.state.source == "osc"
    for _ in range(100):
        r.cycle(C.Live(0, "sacn", r.channels.indices(["brow_l"]), np.array([9.0]), None, r.t))
    assert r.state.source == "sacn" and _deg(r, "brow_l") == pytest.approx(9.0, abs=1e-6)
    assert _deg(r, "jaw") == pytest.approx(5.0, abs=1e-6)  # channels the new source does not send hold
    # a protocol pose takes over from the live input
    r.call(C.Pose, channels=r.channels.indices(["jaw"]), values=np.array([0.0]), speed=1.0)
    assert r.state.mode is Mode.POSE and r.state.source == "api"
    snap = r.call(C.Status)
    assert snap["source"] == "api"


def test_live_watchdog_holds_then_eases_to_neutral() -> None:
    r = Rig()
    r.call(C.Enable)
    for _ in range(60):
        r.cycle(_live(r, "sacn", jaw=8.0))
    events = []
    for _ in range(int(1.2 / r.params.period)):
        events += [e for e in r.cycle().events if e["event"] == "watchdog"]
    assert [e["stage"] for e in events] == ["hold", "neutral"]
    assert all(e["source"] == "sacn" for e in events)
    assert r.state.mode is Mode.NEUTRAL


def test_bundle_with_a_timetag_applies_whole_at_its_time() -> None:
    r = Rig()
    r.call(C.Enable)
    idx = r.channels.indices(["jaw", "brow_l"])
    at = r.t + 0.1
    r.cycle(C.Live(0, "osc", idx, np.array([6.0, 6.0]), at, r.t))
    while r.t < at - 1e-9:
        assert np.isnan(r.state.sources.live.values[idx]).all()
        r.cycle()
    r.cycle()
    assert r.state.sources.live.values[idx].tolist() == [6.0, 6.0]


def _mtc(r: Rig, tc: float, full: bool = False) -> C.Timecode:
    return C.Timecode(0, tc, 25.0, "25", "", r.t, full)


def test_chase_plays_the_clip_at_the_timecode_freewheels_holds_and_relocates() -> None:
    r = ChaseRig(clips=(("ramp", 100.0),), freewheel_s=0.5, dropout_s=0.15, jump_s=0.25, lock_samples=3)
    r.call(C.Enable)
    clip = bind_clip(clip_from_dict(RAMP), r.channels)
    r.call(C.LoadClip, clip=clip, key_count=clip.key_count, nbytes=clip.nbytes)
    tc0, t0 = 104.0, r.t
    events = []
    while r.t < t0 + 1.0:  # a sample every two frames (80 ms at 25 fps)
        cmds = (_mtc(r, tc0 + r.t - t0),) if round((r.t - t0) / r.params.period) % 20 == 0 else ()
        events += [e for e in r.cycle(*cmds).events if e["event"] == "timecode"]
    assert events[0]["change"] == "lock"
    assert r.state.mode is Mode.CLIP and r.state.source == "timecode"
    ct = r.state.timeline.clip_time(r.t)
    assert ct == pytest.approx(tc0 + (r.t - t0) - 100.0, abs=0.01)
    # dropout: freewheel for 0.5 s, then hold
    t_drop = r.t
    while r.t < t_drop + 1.0:
        events += [e for e in r.cycle().events if e["event"] == "timecode"]
    assert [e["change"] for e in events[1:]] == ["freewheel", "hold"]
    held = r.state.timeline.clip_time(r.t)
    assert held == pytest.approx(ct + 0.5, abs=0.1)
    r.cycle()
    assert r.state.timeline.clip_time(r.t) == held
    # a locate relocates the clip, and the clip follows once timecode runs again
    out = r.cycle(_mtc(r, 110.0, full=True))
    assert [e["change"] for e in out.events if e["event"] == "timecode"] == ["jump"]
    assert r.state.timeline.clip_time(r.t) == pytest.approx(10.0)
    status = r.call(C.Status)
    assert status["clock"]["state"] == "hold" and status["clock"]["clip"] == "ramp"


def test_stop_hands_the_head_back_until_the_timecode_relocks_or_jumps() -> None:
    r = ChaseRig(clips=(("ramp", 0.0),), lock_samples=2)
    r.call(C.Enable)
    clip = bind_clip(clip_from_dict(RAMP), r.channels)
    r.call(C.LoadClip, clip=clip, key_count=clip.key_count, nbytes=clip.nbytes)
    for k in range(3):
        r.cycle(_mtc(r, 1.0 + 0.08 * k))
        for _ in range(19):
            r.cycle()
    assert r.state.source == "timecode"
    r.call(C.StopMotion)
    r.cycle(_mtc(r, 1.0 + 0.08 * 3 + 0.02))
    assert r.state.source is None and r.state.mode is Mode.HOLD  # running timecode does not steal it back
    r.cycle(_mtc(r, 5.0))  # a jump does
    assert r.state.source == "timecode" and r.state.mode is Mode.CLIP
