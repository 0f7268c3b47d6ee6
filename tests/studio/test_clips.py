"""Clip documents and ARKit CSV import: the protocol's clip schema, as the daemon validates and evaluates it."""

from __future__ import annotations

import pytest

from models.clip import clip_from_dict
from studio.arkit_csv import ARKIT_BLENDSHAPES, clip_from_live_link_csv, parse_timecode, reduce_keys
from studio.clipdoc import ClipDoc, ClipError


def test_keys_interpolations_and_the_protocol_map() -> None:
    doc = ClipDoc("hi")
    doc.set_key("jaw", 0.0, 0.0, "linear")
    doc.set_key("jaw", 1.0, 10.0)
    doc.set_key("jaw", 0.5, 4.0)
    doc.set_key("jaw", 0.5, 5.0)  # same time: replaces
    assert doc.key_times("jaw") == [0.0, 0.5, 1.0]
    assert doc.sample(0.25)["jaw"] == pytest.approx(2.5)
    doc.set_key("blink", 0.0, 0.0, "step")
    doc.set_key("blink", 0.4, 40.0)
    assert doc.sample(0.39)["blink"] == 0.0 and doc.sample(0.4)["blink"] == 40.0
    doc.set_key("brow_l", 0.0, 0.0, "bezier")
    doc.set_key("brow_l", 0.9, 12.0)
    data = doc.to_dict()
    assert data["channels"]["brow_l"]["keys"] == [[0.0, 0.0, 0.0, 0.0, 0.3, 0.0], [0.9, 12.0, -0.3, 0.0, 0.0, 0.0]]
    clip = clip_from_dict(data)  # the daemon's own validation accepts it and evaluates it alike
    for t in (0.1, 0.45, 0.8):
        assert clip.sample(t) == pytest.approx(doc.sample(t))
    # Ease in and out: the flat Bezier handles make the middle steeper than linear at the start.
    assert 0.0 < doc.sample(0.1)["brow_l"] < 12.0 * 0.1 / 0.9
    assert doc.duration == pytest.approx(1.0)


def test_round_trip_keeps_bezier_handles_and_interp_changes_drop_them(tmp_path) -> None:
    src = {"name": "b", "channels": {"brow_l": {"interp": "bezier",
                                                "keys": [[0, 0, 0, 0, 0.2, 5], [1.0, 20, -0.1, -2, 0, 0]]}}}
    doc = ClipDoc.from_dict(src)
    assert doc.to_dict()["channels"]["brow_l"]["keys"] == [[0.0, 0.0, 0.0, 0.0, 0.2, 5.0],
                                                           [1.0, 20.0, -0.1, -2.0, 0.0, 0.0]]
    path = doc.save(tmp_path / "b.json")
    assert ClipDoc.load(path).to_dict() == doc.to_dict()
    doc.set_interp("brow_l", "linear")
    assert doc.to_dict()["channels"]["brow_l"]["keys"] == [[0.0, 0.0], [1.0, 20.0]]
    assert doc.remove_key("brow_l", 1.0) and doc.remove_key("brow_l", 0.0)
    assert "brow_l" not in doc.tracks


def test_bad_clips_and_edits_are_refused_naming_what() -> None:
    with pytest.raises(ClipError, match="times must increase"):
        ClipDoc.from_dict({"name": "x", "channels": {"jaw": {"keys": [[0, 0], [0, 1]]}}})
    with pytest.raises(ClipError, match="not JSON"):
        ClipDoc.from_json("{", "f.json")
    doc = ClipDoc("x")
    with pytest.raises(ClipError, match="no keys"):
        doc.to_dict()
    with pytest.raises(ClipError, match="finite"):
        doc.set_key("jaw", 0.0, float("nan"))
    with pytest.raises(ClipError, match="interpolation"):
        doc.set_key("jaw", 0.0, 1.0, "cubic")
    doc.set_key("nose", 0.0, 1.0)
    with pytest.raises(ClipError, match="not on this head: nose"):
        doc.check_channels({"jaw": 1})


def _live_link_csv(rows: list[tuple[str, dict[str, float]]]) -> str:
    names = [n[0].upper() + n[1:] for n in ARKIT_BLENDSHAPES]
    head = ["Timecode", "BlendShapeCount", *names, "HeadYaw", "HeadPitch", "HeadRoll"]
    lines = [",".join(head)]
    for tc, values in rows:
        lines.append(",".join([tc, "61", *(f"{values.get(n, 0.0):.4f}" for n in ARKIT_BLENDSHAPES), "0.1", "0", "0"]))
    return "\n".join(lines) + "\n"


def test_live_link_face_csv_becomes_a_clip_of_arkit_channels() -> None:
    rows = [(f"12:00:01:{f:02d}.000", {"jawOpen": min(1.0, f / 10), "eyeBlinkLeft": 1.0 if f == 5 else 0.0})
            for f in range(0, 30)]
    doc = clip_from_live_link_csv(_live_link_csv(rows), "take", fps=60.0,
                                  channels=["arkit.jawOpen", "arkit.eyeBlinkLeft", "arkit.browInnerUp"])
    assert set(doc.tracks) == {"arkit.jawOpen", "arkit.eyeBlinkLeft"}  # browInnerUp stays at zero
    jaw = doc.tracks["arkit.jawOpen"]
    assert jaw.keys[0].t == 0.0 and jaw.keys[-1].t == pytest.approx(29 / 60)
    assert len(jaw.keys) == 3  # a ramp, then a hold: the linear stretches need no inner keys
    assert doc.sample(5 / 60)["arkit.jawOpen"] == pytest.approx(0.5, abs=1e-3)
    assert doc.sample(5 / 60)["arkit.eyeBlinkLeft"] == pytest.approx(1.0)
    assert doc.sample(7 / 60)["arkit.eyeBlinkLeft"] == pytest.approx(0.0)
    clip_from_dict(doc.to_dict())


def test_live_link_csv_errors_name_the_problem() -> None:
    with pytest.raises(ClipError, match="Timecode"):
        clip_from_live_link_csv("time,jawOpen\n0,1\n", "x")
    text = _live_link_csv([("00:00:00:00.000", {})]).replace("JawOpen", "JawOpened")
    with pytest.raises(ClipError, match="lacks 1 of the 52 ARKit blendshape columns: jawOpen"):
        clip_from_live_link_csv(text, "x")
    rows = [("00:00:00:01.000", {"jawOpen": 0.5}), ("00:00:00:01.000", {"jawOpen": 0.6})]
    with pytest.raises(ClipError, match=r"row 3: timecode .* does not advance"):
        clip_from_live_link_csv(_live_link_csv(rows), "x")
    with pytest.raises(ClipError, match="bad timecode"):
        parse_timecode("1:2:3", 60.0, "row 2")
    assert parse_timecode("01:00:02:30.5", 60.0, "r") == pytest.approx(3602 + 30.5 / 60)


def test_reduce_keys_keeps_corners_within_tolerance() -> None:
    t = [0.0, 1.0, 2.0, 3.0, 4.0]
    v = [0.0, 1.0, 2.0, 2.0, 2.0]
    assert reduce_keys(t, v, 1e-9) == [0, 2, 4]
