"""Moving keys and setting Bezier handles in a clip, undo and redo, and the timeline state the page draws."""

from __future__ import annotations

import numpy as np
import pytest

from models.clip import clip_from_dict
from studio.clipdoc import ClipDoc, ClipError
from studio.timeline import Audio, timeline_length, timeline_state

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


def test_the_timeline_state_has_every_track_its_keys_handles_and_curve() -> None:
    doc = _doc()
    state = timeline_state(doc, RANGES, ORDER, length=3.0, playhead=1.25, selected=("blink", 1),
                           audio=Audio("take.wav", 4.5))
    assert [t["name"] for t in state["tracks"]] == ["jaw", "blink"]  # the head's channel order
    jaw, blink = state["tracks"]
    assert (jaw["interp"], jaw["lo"], jaw["hi"]) == ("linear", 0.0, 20.0)
    assert jaw["keys"] == [[0.0, 0.0], [1.0, 10.0], [2.0, 5.0]]
    assert blink["keys"][0] == pytest.approx([0.5, 1.0, 0.0, 0.0, 1.0 / 3.0, 0.0])  # handles as the clip uses them
    assert state["length"] == 4.5 and state["playhead"] == 1.25 and state["selected"] == ["blink", 1]
    assert state["audio"] == {"name": "take.wav", "duration": 4.5}
    # The curve is the clip's own evaluation, through every key.
    t, v = np.array(jaw["curve"]["t"]), np.array(jaw["curve"]["v"])
    assert np.all(np.diff(t) > 0) and t[0] == 0.0 and t[-1] == pytest.approx(4.5)
    for key_t, key_v in jaw["keys"]:
        assert v[np.flatnonzero(t == key_t)[0]] == pytest.approx(key_v)
    curve = clip_from_dict(doc.to_dict()).channels["blink"]
    bt, bv = blink["curve"]["t"], blink["curve"]["v"]
    assert all(abs(curve.value(x) - y) < 1e-6 for x, y in zip(bt, bv, strict=True))
    assert timeline_state(doc, RANGES, ORDER, 3.0, 0.0, selected=("jaw", 7))["selected"] is None
    assert timeline_length(doc, 1.0, None) == 2.0  # the last key


def test_every_edit_undoes_and_redoes_and_a_batch_is_one_step() -> None:
    doc = ClipDoc("u")
    assert not doc.can_undo
    doc.set_key("jaw", 0.0, 0.0)
    doc.set_key("jaw", 1.0, 5.0)
    doc.move_key("jaw", 1, 1.5, 4.0)
    assert doc.undo() and doc.to_dict()["channels"]["jaw"]["keys"] == [[0.0, 0.0], [1.0, 5.0]]
    assert doc.undo() and doc.key_times("jaw") == [0.0]
    assert doc.redo() and doc.redo() and doc.to_dict()["channels"]["jaw"]["keys"] == [[0.0, 0.0], [1.5, 4.0]]
    assert not doc.redo()
    doc.undo()
    doc.set_key("blink", 0.0, 1.0)  # a new edit drops what could be redone
    assert not doc.can_redo
    with doc.batch():
        doc.set_key("brow_l", 0.0, 1.0)
        doc.set_key("brow_l", 1.0, 2.0)
        doc.set_interp("brow_l", "bezier")
    doc.undo()
    assert "brow_l" not in doc.tracks and "blink" in doc.tracks
    version = doc.version
    assert doc.undo() and doc.version > version  # views redraw after an undo
    assert "blink" not in doc.tracks
    assert not ClipDoc.from_dict(doc.to_dict()).can_undo  # a loaded clip starts its own history
