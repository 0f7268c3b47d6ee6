"""The Blender add-on's parts that need no Blender: clip keys ↔ Blender keys (exact, through 32-bit storage),
recordings as clips, the live link's timeline clock and the add-on's install files."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from models.clip import ClipError, clip_from_dict
from studio.blender.curves import (
    ExactKeys,
    Keyframe,
    TimeBase,
    channel_from_keyframes,
    channel_interp,
    keyframes_from_channel,
)
from studio.blender.live import FrameClock
from tests.blender.conftest import write_lrec

CLIP = {"name": "probe", "channels": {
    "jaw": {"interp": "bezier", "keys": [[0.0, 0.0, 0.0, 0.0, 0.21, 3.3],
                                         [0.8123456789, 37.123456789, -0.2, 1.7, 0.3, -2.1],
                                         [61.3, 12.5, -0.4, 0.0, 0.0, 0.0]]},
    "blink": {"interp": "step", "keys": [[0.0, 0.0], [0.4, 40.0], [0.55, 0.0]]},
    "arkit.jawOpen": {"interp": "linear", "keys": [[0.0, 0.0], [0.5, 0.7], [1.0, 0.123456789]]},
}}


def _through_float32(keys: list[Keyframe]) -> list[Keyframe]:
    """What an F-curve gives back: every number rounded to 32 bits."""
    out = []
    for k in keys:
        f, v, lf, lv, rf, rv = k.rounded()
        out.append(Keyframe(f, v, (lf, lv), (rf, rv), k.interpolation))
    return out


def test_round_trip_through_32_bit_keys_is_exact_with_the_recorded_keys() -> None:
    base = TimeBase(24.0, 1.0)
    exact = ExactKeys.from_json(json.loads(json.dumps(ExactKeys.of_clip(CLIP, base).to_json())))
    for ch, spec in CLIP["channels"].items():
        stored = _through_float32(keyframes_from_channel(spec, base, ch))
        out = channel_from_keyframes(stored, base, ch, exact.lookup(ch, base))
        assert out["interp"] == spec["interp"]
        assert np.array_equal(np.array(out["keys"]), np.array(spec["keys"]))
        # Without the recorded keys, 32-bit storage alone loses more than 1e-6 (why they are recorded).
        lossy = channel_from_keyframes(stored, base, ch)
        if ch == "jaw":
            assert np.abs(np.array(lossy["keys"]) - np.array(spec["keys"])).max() > 1e-6
    # A changed time base ignores the recorded keys rather than misplacing them.
    assert exact.lookup("jaw", TimeBase(30.0, 1.0)) == {}


def test_an_edited_key_exports_its_new_numbers_and_handles_become_offsets() -> None:
    base = TimeBase(25.0, 0.0)
    spec = CLIP["channels"]["jaw"]
    stored = _through_float32(keyframes_from_channel(spec, base, "jaw"))
    moved = Keyframe(stored[1].frame + 2.0, 30.0, (stored[1].left[0] + 2.0, 31.0), (stored[1].right[0] + 2.0, 29.0),
                     "BEZIER")
    out = channel_from_keyframes([stored[0], moved, stored[2]], base, "jaw",
                                 ExactKeys.of_clip(CLIP, base).lookup("jaw", base))
    assert out["keys"][0] == spec["keys"][0] and out["keys"][2] == spec["keys"][2]
    t, v, idt, idv, odt, odv = out["keys"][1]
    assert t == pytest.approx(moved.frame / 25.0) and v == 30.0
    assert (idt, idv, odt, odv) == pytest.approx((-0.2, 1.0, 0.3, -1.0), abs=1e-5)


def test_mixed_interpolations_export_exactly_or_say_why_not() -> None:
    def kf(f: float, v: float, interp: str) -> Keyframe:
        return Keyframe(f, v, (f - 1, v), (f + 1, v), interp)

    base = TimeBase(10.0, 0.0)
    mixed = [kf(0, 0, "LINEAR"), kf(3, 3, "BEZIER"), kf(6, 0, "LINEAR")]
    out = channel_from_keyframes(mixed, base, "jaw")
    assert out["interp"] == "bezier"
    curve = clip_from_dict({"name": "m", "channels": {"jaw": out}}).channels["jaw"]
    for t in (0.05, 0.1, 0.2, 0.25):  # the linear segment stays a straight line
        assert curve.value(t) == pytest.approx(10 * t, abs=1e-9)
    with pytest.raises(ClipError, match=r"frame 3.*CONSTANT.*resampling"):
        channel_interp([kf(0, 0, "LINEAR"), kf(3, 1, "CONSTANT"), kf(6, 0, "LINEAR")], "head.jaw")
    with pytest.raises(ClipError, match=r"frame 0.*ELASTIC"):
        channel_interp([kf(0, 0, "ELASTIC"), kf(3, 1, "LINEAR")], "head.jaw")


def test_frame_clock_follows_the_timeline_without_drift_and_reanchors_on_jumps() -> None:
    clock = FrameClock(lead=0.1, tolerance=0.05)
    fps = 24.0
    t0 = clock.stamp(1, fps, now=100.0)
    assert t0 == pytest.approx(100.1)
    # Real-time playback with jittery draw times: stamps keep the exact frame spacing.
    rng = np.random.default_rng(1)
    stamps = [clock.stamp(f, fps, now=100.0 + (f - 1) / fps + rng.uniform(-0.02, 0.02)) for f in range(2, 200)]
    assert np.allclose(np.diff([t0, *stamps]), 1 / fps, atol=1e-9) and clock.anchors == 1
    # Frames skipped to keep up (Blender's frame dropping, Sync to Audio) keep the timeline's stamps.
    assert clock.stamp(203, fps, now=100.0 + 202 / fps + 0.01) == pytest.approx(stamps[-1] + 4 / fps)  # after 199
    assert clock.anchors == 1
    # A scrub back re-anchors at now + lead.
    assert clock.stamp(50, fps, now=200.0) == pytest.approx(200.1) and clock.anchors == 2
    # Playback slower than real time: stamps fall behind now + lead, so the clock re-anchors within tolerance.
    now = 200.0
    for f in range(51, 120):
        now += 2 / fps  # half speed
        t = clock.stamp(f, fps, now)
        assert abs(t - (now + 0.1)) <= 0.05 + 1e-9
    assert clock.anchors > 3
    # Playback faster than real time: re-anchored, yet a later frame is never stamped before an earlier one.
    last = clock.stamp(120, fps, now)
    for f in range(121, 200):
        now += 0.2 / fps
        t = clock.stamp(f, fps, now)
        assert t > last
        last = t


def test_recording_becomes_a_linear_clip_of_its_commanded_or_measured_curves(tmp_path: Path) -> None:
    from studio.blender.recording import recording_clip

    t = np.arange(0, 1.0, 0.004)
    rows = np.column_stack([t + 5.0, 10 * t, np.full_like(t, 3.0), 10 * t - 0.5, np.full_like(t, np.nan)])
    path = write_lrec(tmp_path / "take.lrec", ["jaw", "blink"], rows, tail=b"\x00" * 12)  # a cut last record
    clip = recording_clip(path, "commanded", step=1 / 24)
    jaw = np.array(clip["channels"]["jaw"]["keys"])
    assert jaw[0, 0] == 0.0 and jaw[-1, 0] == pytest.approx(t[-1]) and len(jaw) in (25, 26)
    assert np.allclose(jaw[:, 1], 10 * jaw[:, 0])
    measured = recording_clip(path, "measured")
    assert set(measured["channels"]) == {"jaw"}  # blink was never measured (NaN)
    clip_from_dict(measured)
    (tmp_path / "bad.lrec").write_bytes(b'{"format": "other"}\n')
    with pytest.raises(ValueError, match=r"bad\.lrec: header: not a recording"):
        recording_clip(tmp_path / "bad.lrec")


def test_install_writes_the_addon_package_and_the_zip(tmp_path: Path) -> None:
    from models.errors import UsageError
    from studio.blender.install import ADDON, build_zip, install, user_addon_dir

    folder = install(tmp_path / "addons")
    shim = (folder / "__init__.py").read_text()
    assert folder.name == ADDON and "bl_info" in shim and str(Path(__file__).resolve().parents[2]) in shim
    compile(shim, "__init__.py", "exec")
    with zipfile.ZipFile(build_zip(tmp_path / "a.zip")) as z:
        assert sorted(z.namelist()) == [f"{ADDON}/__init__.py", f"{ADDON}/blender_manifest.toml"]
    env = {"HOME": "/home/a"}
    assert user_addon_dir("5.0", "linux", env) == Path("/home/a/.config/blender/5.0/scripts/addons")
    assert user_addon_dir("4.2.1", "darwin", env) == Path(
        "/home/a/Library/Application Support/Blender/4.2/scripts/addons")
    assert user_addon_dir("5.0", "linux", {**env, "BLENDER_USER_SCRIPTS": "/s"}) == Path("/s/addons")
    with pytest.raises(UsageError, match=r"MAJOR\.MINOR"):
        user_addon_dir("five", "linux", env)


def test_the_command_installs_and_zips_the_addon(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from likeness.cli import main

    assert main(["blender", "install", "--target", str(tmp_path / "addons")]) == 0
    assert (tmp_path / "addons" / "likeness_blender" / "__init__.py").is_file()
    assert "enable 'Likeness'" in capsys.readouterr().out
    assert main(["blender", "zip", "--out", str(tmp_path / "l.zip")]) == 0
    assert zipfile.is_zipfile(tmp_path / "l.zip")
    assert main(["blender", "install", "--blender-version", "x", "--target", str(tmp_path)]) == 0  # target wins
    assert main(["blender", "install", "--blender-version", "x"]) == 2  # a usage error, one line
    assert "MAJOR.MINOR" in capsys.readouterr().err
