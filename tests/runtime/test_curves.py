"""Keyframe curves and clip files: interpolation modes, Bezier tangents, validation errors naming the culprit."""

from __future__ import annotations

import json
import math

import pytest

from models.clip import ClipError, clip_from_csv, clip_from_dict, load_clip_file, make_curve


def test_step_and_linear_hold_outside_and_interpolate_inside() -> None:
    step = make_curve("step", [[0, 1], [1, 3], [2, -1]])
    lin = make_curve("linear", [[0, 1], [1, 3], [2, -1]])
    assert step.value(-5) == 1 and step.value(0.99) == 1 and step.value(1.0) == 3 and step.value(9) == -1
    assert lin.value(0.5) == pytest.approx(2.0) and lin.value(1.5) == pytest.approx(1.0)
    assert lin.value(-1) == 1 and lin.value(3) == -1


def test_bezier_with_linear_handles_is_a_line_and_flat_handles_ease() -> None:
    # Handles on the straight line between keys reproduce linear interpolation.
    line = make_curve("bezier", [[0, 0, 0, 0, 1 / 3, 10 / 3], [1, 10, -1 / 3, -10 / 3, 0, 0]])
    for t in (0.1, 0.25, 0.5, 0.9):
        assert line.value(t) == pytest.approx(10 * t, abs=1e-6)
    # Flat tangents ease in and out: symmetric, slower than linear near the keys.
    ease = make_curve("bezier", [[0, 0, 0, 0, 0.5, 0], [2, 10, -0.5, 0, 0, 0]])
    assert ease.value(1.0) == pytest.approx(5.0, abs=1e-6)
    assert ease.value(0.2) < 1.0 and ease.value(1.8) > 9.0
    assert ease.value(0.5) == pytest.approx(10 - ease.value(1.5), abs=1e-6)


def test_bezier_overlong_handles_stay_monotonic_in_time() -> None:
    c = make_curve("bezier", [[0, 0, 0, 0, 5.0, 20.0], [1, 1, -5.0, 0, 0, 0]])
    values = [c.value(i / 100) for i in range(101)]
    assert all(math.isfinite(v) for v in values)
    assert values[0] == 0 and values[-1] == 1


@pytest.mark.parametrize(
    ("interp", "keys", "fragment"),
    [
        ("cubic", [[0, 1]], "interp"),
        ("linear", [], "non-empty"),
        ("linear", [[0, 1], [0, 2]], "increase strictly"),
        ("linear", [[0, float("nan")]], "keys[0][1]"),
        ("linear", [[0, 1, 2]], "keys[0]"),
        ("bezier", [[0, 1]], "6 numbers"),
        ("bezier", [[0, 1, 0.1, 0, 0, 0]], "in_dt <= 0"),
        ("linear", [[0, True]], "finite number"),
    ],
)
def test_bad_keys_name_the_problem(interp: str, keys: list, fragment: str) -> None:
    with pytest.raises(ClipError, match=None) as info:
        make_curve(interp, keys, "clip 'x'.channels.jaw")
    assert fragment in str(info.value)
    assert "jaw" in str(info.value)


def test_clip_dict_validation() -> None:
    clip = clip_from_dict({"name": "c", "channels": {"jaw": {"keys": [[0, 0], [2, 5]], "interp": "linear"}}})
    assert clip.duration == 2 and clip.sample(1) == {"jaw": pytest.approx(2.5)}
    with pytest.raises(ClipError, match="name"):
        clip_from_dict({"channels": {}})
    with pytest.raises(ClipError, match="unknown key"):
        clip_from_dict({"name": "c", "channels": {"jaw": {"keys": [[0, 0]], "bogus": 1}}})
    with pytest.raises(ClipError, match="channels"):
        clip_from_dict({"name": "c", "channels": []})


def test_csv_clip_and_errors_name_row_and_column(tmp_path) -> None:
    clip = clip_from_csv("time,jaw,brow_l\n0,0,1\n1,10,\n2,0,3\n", "c")
    assert clip.channels["jaw"].value(0.5) == pytest.approx(5)
    assert clip.channels["brow_l"].times == (0.0, 2.0)
    with pytest.raises(ClipError, match=r"row 3, column 'jaw'"):
        clip_from_csv("time,jaw\n0,1\n1,abc\n", "c", source="f.csv")
    with pytest.raises(ClipError, match="row 1 column 1"):
        clip_from_csv("jaw,time\n0,1\n", "c")
    path = tmp_path / "p.csv"
    path.write_text("t,jaw\n0,0\n1,5\n")
    assert load_clip_file(path).name == "p"


def test_bundled_performance_covers_all_actuators_and_interpolations() -> None:
    from pathlib import Path

    from models.headspec import load_head

    root = Path(__file__).resolve().parents[2]
    head = load_head(root / "heads" / "sample" / "head.toml")
    perf = root / "heads" / "sample" / "performances" / "expressive.json"
    clip = load_clip_file(perf)
    assert set(clip.channels) == set(head.actuator_names)
    assert {c.interp for c in clip.channels.values()} == {"bezier", "linear", "step"}
    assert clip.duration >= 5.0
    for name, curve in clip.channels.items():
        act = head.actuator(name)
        lo, hi = act.to_config_units(act.min), act.to_config_units(act.max)
        assert all(lo <= curve.value(i * 0.01) <= hi for i in range(int(clip.duration * 100)))
    assert json.loads(perf.read_text())["name"] == clip.name
