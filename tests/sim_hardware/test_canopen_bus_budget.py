"""Frame-time arithmetic of the CANopen bus-cycle benchmark (checked against hand-computed CAN 2.0A sizes)."""

from __future__ import annotations

import pytest

from benchmarks._bus_canopen import can_budget, can_frame_bits


def test_can_frame_bits():
    assert can_frame_bits(0) == 47  # SYNC
    assert can_frame_bits(8) == 111
    assert can_frame_bits(8, worst_case_stuffing=True) == 111 + 24
    with pytest.raises(ValueError):
        can_frame_bits(9)


def test_budget_of_thirteen_drives():
    budget = can_budget(13, (8, 8))
    # 1 SYNC + 26 eight-byte frames at 1 Mbit/s.
    assert budget["frames_per_cycle"] == 27
    assert budget["cycle_s_nominal"] == pytest.approx((47 + 26 * 111) / 1e6)
    # FACTS.md: about 230 Hz for 13 drives at 70 % load without stuffing; worst-case stuffing lowers it.
    assert 0.7 / budget["cycle_s_nominal"] == pytest.approx(230, rel=0.05)
    assert budget["max_rate_hz_at_70pct_load"] < 0.7 / budget["cycle_s_nominal"]
