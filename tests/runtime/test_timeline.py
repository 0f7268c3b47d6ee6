"""Show-time playback (play at, speed, loop, pause, seek) and the jitter buffer (late frames dropped, counted)."""

from __future__ import annotations

import numpy as np
import pytest

from models.clip import clip_from_dict
from runtime.core.stream import StreamBuffer
from runtime.timeline import Timeline


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


def _push(sb: StreamBuffer, now: float, t: float, value: float, channel: int = 0) -> str:
    counts = sb.push(now, np.array([t]), np.array([channel]), np.array([[value]]))
    return next(k for k, v in counts.items() if v)


def test_stream_buffer_interpolates_after_delay_and_drops_late_frames() -> None:
    sb = StreamBuffer(n_channels=2, delay=0.1, max_frames=100, max_ahead=5.0)
    out = np.empty(2)
    assert _push(sb, 10.0, 10.0, 0.0) == "ok"
    assert _push(sb, 10.0, 10.2, 2.0) == "ok"
    assert _push(sb, 10.0, 10.1, 1.0) == "ok"  # reordered in transit: absorbed
    assert not sb.evaluate(10.05, out)  # play-out time 9.95 is before the first frame
    assert sb.evaluate(10.15, out) and out[0] == pytest.approx(0.5) and np.isnan(out[1])
    assert _push(sb, 10.16, 10.02, 9.0) == "late"
    assert sb.evaluate(10.35, out) and out[0] == pytest.approx(2.0)  # held after the last frame
    assert _push(sb, 10.35, 30.0, 1.0) == "ahead"
    assert sb.late == 1 and sb.accepted == 3
    assert sb.starved_for(10.35) == pytest.approx(0.35)  # since the last frame received


def test_stream_buffer_capacity_and_bulk_append() -> None:
    sb = StreamBuffer(n_channels=1, delay=0.0, max_frames=3, max_ahead=5.0)
    results = [_push(sb, 0.0, 0.1 * i, 1.0) for i in range(1, 6)]
    assert results == ["ok", "ok", "ok", "full", "full"] and sb.overflow == 2
    sb = StreamBuffer(n_channels=2, delay=0.0, max_frames=50, max_ahead=100.0)
    out = np.empty(2)
    for batch in range(10):  # in-order batches, played out as they come: the rows are reused
        times = 10.0 + batch + 0.1 * np.arange(10)
        assert sb.push(9.0 + batch, times, np.array([1]), times[:, None])["ok"] == 10
        assert sb.evaluate(10.05 + batch + 0.5, out) and out[1] == pytest.approx(10.05 + batch + 0.5)
    assert sb.count <= 50


def test_stream_buffer_mixed_channels_interpolate_where_both_frames_carry_them() -> None:
    sb = StreamBuffer(n_channels=3, delay=0.0, max_frames=10, max_ahead=5.0)
    sb.push(0.0, np.array([1.0]), np.array([0, 1]), np.array([[0.0, 10.0]]))
    sb.push(0.0, np.array([2.0]), np.array([1, 2]), np.array([[20.0, 5.0]]))
    out = np.empty(3)
    assert sb.evaluate(1.5, out)
    assert out.tolist() == [0.0, 15.0, 5.0]
