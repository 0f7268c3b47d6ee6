"""Show-time playback (play at, speed, loop, pause, seek) and the jitter buffer (late frames dropped, counted)."""

from __future__ import annotations

import pytest

from runtime.curves import clip_from_dict
from runtime.timeline import JitterBuffer, Timeline


def _clip():
    return clip_from_dict({"name": "ramp", "channels": {"jaw": {"keys": [[0, 0], [2, 20]], "interp": "linear"}}})


def test_play_at_speed_pause_resume_seek_loop() -> None:
    tl = Timeline()
    tl.load(_clip())
    tl.play("ramp", now=100.0, at=101.0, offset=0.0, speed=2.0, loop=False)
    assert tl.evaluate(100.5) is None  # not started yet
    assert tl.evaluate(101.5)["jaw"] == pytest.approx(10.0)
    tl.pause(101.5)
    assert tl.evaluate(105.0)["jaw"] == pytest.approx(10.0)
    tl.resume(105.0)
    assert tl.evaluate(105.25)["jaw"] == pytest.approx(15.0)
    tl.seek(106.0, 0.5)
    assert tl.evaluate(106.0)["jaw"] == pytest.approx(5.0)
    assert tl.finished(110.0) and tl.evaluate(110.0)["jaw"] == 20.0
    tl.play("ramp", now=200.0, at=None, offset=0.0, speed=1.0, loop=True)
    assert tl.evaluate(202.5)["jaw"] == pytest.approx(5.0)
    assert not tl.finished(250.0)


def test_jitter_buffer_interpolates_after_delay_and_drops_late_frames() -> None:
    jb = JitterBuffer(delay=0.1, max_frames=100, max_ahead=5.0)
    assert jb.push(10.0, 10.0, {"jaw": 0.0}) == "ok"
    assert jb.push(10.0, 10.2, {"jaw": 2.0}) == "ok"
    assert jb.push(10.0, 10.1, {"jaw": 1.0}) == "ok"  # reordered in transit: absorbed
    assert jb.evaluate(10.05) is None  # play-out time 9.95 is before the first frame
    assert jb.evaluate(10.15)["jaw"] == pytest.approx(0.5)
    assert jb.push(10.16, 10.02, {"jaw": 9.0}) == "late"
    assert jb.evaluate(10.35)["jaw"] == pytest.approx(2.0)  # held after the last frame
    assert jb.push(10.35, 30.0, {"jaw": 1.0}) == "ahead"
    assert jb.late == 1 and jb.accepted == 3
    assert jb.starved_for(10.35) == pytest.approx(0.05)


def test_jitter_buffer_capacity() -> None:
    jb = JitterBuffer(delay=0.0, max_frames=3, max_ahead=5.0)
    results = [jb.push(0.0, 0.1 * i, {"a": 1.0}) for i in range(1, 6)]
    assert results == ["ok", "ok", "ok", "full", "full"] and jb.overflow == 2
