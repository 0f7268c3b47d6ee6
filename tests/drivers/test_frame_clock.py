"""The CANopen driver stamps feedback with the time its frame was on the bus: a backlog read late shows its age, a
remote clock's constant offset cancels out, and an implausible stamp counts as just received."""

from __future__ import annotations

import time

import pytest

from drivers.canopen402 import MAX_FRAME_AGE_S, FrameClock


def test_a_frame_read_late_keeps_its_age() -> None:
    clock = FrameClock()
    clock.reported_at(time.time())  # the transport at its quickest: no delay
    stamp = clock.reported_at(time.time() - 0.3)  # a frame that waited 0.3 s to be read
    assert time.monotonic() - stamp == pytest.approx(0.3, abs=0.05)


def test_a_remote_clock_offset_cancels_out() -> None:
    clock = FrameClock()
    skew = 2.5  # the server's clock runs behind this host's
    assert time.monotonic() - clock.reported_at(time.time() - skew) == pytest.approx(0.0, abs=0.05)
    assert time.monotonic() - clock.reported_at(time.time() - skew - 0.2) == pytest.approx(0.2, abs=0.05)
    assert time.monotonic() - clock.reported_at(time.time() - skew + 0.001) == pytest.approx(0.0, abs=0.05)


@pytest.mark.parametrize("frame_time", [0.0, float("nan"), -1.0])
def test_implausible_stamps_count_as_just_received(frame_time: float) -> None:
    clock = FrameClock()
    assert time.monotonic() - clock.reported_at(frame_time) < 0.05


def test_a_clock_step_is_not_believed() -> None:
    clock = FrameClock()
    clock.reported_at(time.time())
    assert time.monotonic() - clock.reported_at(time.time() - 2 * MAX_FRAME_AGE_S) < 0.05
