"""Capture stream frames: built and validated by models.capture."""

from __future__ import annotations

import pytest

from models.capture import MarkerSample, frame_body, samples_from_body


def test_frame_body_round_trip_and_validation() -> None:
    samples = [MarkerSample(1.5, "jaw", (0.0, -0.08, 0.07), (1.0, 0.0, 0.0, 0.0))]
    body = frame_body(3, samples)
    assert body["v"] == 1 and body["frame"] == 3
    assert samples_from_body(body) == samples
    for bad, msg in [
        ({**body, "v": 2}, "unsupported"),
        ({**body, "time": "x"}, "numeric 'time'"),
        ({**body, "markers": {"jaw": [0, 0, 0]}}, "marker 'jaw'"),
        ({**body, "markers": {"jaw": [0, 0, 0, 0, 0, 0, 0]}}, "non-zero quaternion"),
    ]:
        with pytest.raises(ValueError, match=msg):
            samples_from_body(bad)
