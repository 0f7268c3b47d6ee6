"""Moving keys and setting Bezier handles in a clip, and the multi-track timeline chart built from it."""

from __future__ import annotations

import numpy as np
import pytest

from models.clip import clip_from_dict
from studio.clipdoc import ClipDoc, ClipError
from studio.timeline import row_y, timeline_chart

RANGES = {"jaw": (0.0, 20.0), "blink": (0.0, 1.0), "brow_l": (-10.0, 10.0)}
ORDER = ("jaw", "brow_l", "blink")


def _doc() -> ClipDoc:
    doc = ClipDoc("moves")
    doc.set_key("jaw", 0.0, 0.0, "linear")
    doc.set_key("jaw", 1.0, 10.0)
    doc.set_key("jaw", 2.0, 5.0)
    doc.set_key("blink", 0.5, 1.0, "bezier")
    doc.set_key("blink", 1.5, 0.0)
    return doc


def test_moving_a_key_keeps_keys_sorted_and_refuses_a_taken_time() -> None:
    doc = _doc()
    assert doc.move_key("jaw", 0, 1.5, 2.0) == 1  # past its neighbour: now the second key
    assert doc.to_dict()["channels"]["jaw"]["keys"] == [[1.0, 10.0], [1.5, 2.0], [2.0, 5.0]]
    with pytest.raises(ClipError, match=r"already has a key at 2\.000 s"):
        doc.move_key("jaw", 1, 2.0, 0.0)
    with pytest.raises(ClipError, match="no key #4"):
        doc.move_key("jaw", 3, 0.1, 0.0)
    with pytest.raises(ClipError, match=">= 0 s"):
        doc.move_key("jaw", 0, -0.1, 0.0)
    with pytest.raises(ClipError, match="no keys"):
        doc.move_key("brow_l", 0, 0.1, 0.0)
    clip_from_dict(doc.to_dict())  # still a clip the daemon accepts


def test_bezier_handles_are_set_validated_and_kept_when_a_neighbour_moves() -> None:
    doc = _doc()
    assert doc.handles("blink", 0) == pytest.approx((0.0, 0.0, 1.0 / 3.0, 0.0))  # automatic: flat, a third
    doc.set_handles("blink", 0, (-0.2, 0.0, 0.6, 0.5))
    doc.move_key("blink", 1, 2.5, 0.0)  # the neighbour moves: the set handles stay, the automatic ones follow
    rows = doc.to_dict()["channels"]["blink"]["keys"]
    assert rows[0] == [0.5, 1.0, -0.2, 0.0, 0.6, 0.5]
    assert rows[1][2] == pytest.approx(-2.0 / 3.0)
    # The handles shape the curve: a rising out-handle lifts it above the flat-handle version early on.
    flat = _doc()
    flat.move_key("blink", 1, 2.5, 0.0)
    assert doc.sample(0.7)["blink"] > flat.sample(0.7)["blink"]
    assert clip_from_dict(doc.to_dict()).sample(0.7)["blink"] == pytest.approx(doc.sample(0.7)["blink"])
    with pytest.raises(ClipError, match="in_dt <= 0 <= out_dt"):
        doc.set_handles("blink", 0, (0.1, 0.0, 0.2, 0.0))
    with pytest.raises(ClipError, match="not bezier"):
        doc.set_handles("jaw", 0, (-0.1, 0.0, 0.1, 0.0))
    with pytest.raises(ClipError, match="finite"):
        doc.set_handles("blink", 0, (-0.1, float("nan"), 0.1, 0.0))


def test_the_timeline_has_a_row_per_track_keys_the_selected_key_and_the_playhead() -> None:
    doc = _doc()
    chart = timeline_chart(doc, RANGES, ORDER, end=3.0, playhead=1.25, selected=("blink", 1))
    assert chart.tracks == ("jaw", "blink")  # the head's channel order
    x = chart.data[0]
    assert len(chart.data) == len(chart.series) == 1 + 2 * 2 + 2
    assert all(len(d) == len(x) for d in chart.data) and np.all(np.diff(x) >= 0)
    jaw_curve, jaw_keys, blink_curve, blink_keys, selected, playhead = chart.data[1:]
    # jaw on the top row (1..2), blink below (0..1), each within its row
    assert np.nanmin(jaw_curve) >= 1.0 and np.nanmax(jaw_curve) <= 2.0
    assert np.nanmin(blink_curve) >= 0.0 and np.nanmax(blink_curve) <= 1.0
    assert jaw_curve[np.argmin(np.abs(x - 1.0))] == pytest.approx(row_y(10.0, 0, 2, 0.0, 20.0))
    assert np.count_nonzero(np.isfinite(jaw_keys)) == 3 and np.count_nonzero(np.isfinite(blink_keys)) == 2
    (sel,) = np.flatnonzero(np.isfinite(selected))
    assert x[sel] == pytest.approx(1.5) and selected[sel] == pytest.approx(row_y(0.0, 1, 2, 0.0, 1.0))
    ph = np.flatnonzero(np.isfinite(playhead))
    assert list(x[ph]) == [1.25, 1.25] and list(playhead[ph]) == [0.0, 2.0]  # a vertical line across both rows
    assert chart.scales["y"] == {"auto": False, "range": [0.0, 2.0]}  # fixed: the key series are mostly gaps
    with pytest.raises(ValueError, match="length"):
        timeline_chart(doc, RANGES, ORDER, end=0.0, playhead=0.0)
