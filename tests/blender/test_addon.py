"""The add-on inside Blender (``bpy`` as a module): the sample head as a mesh whose channels drive the predicted skin,
its strain colours and verdict, clips in and out of actions exactly, and the generated add-on package registering."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.clip import clip_from_dict
from studio.head import StudioHead
from tests.blender.conftest import SAMPLE, write_lrec


@pytest.fixture(scope="module")
def reference() -> StudioHead:
    """The sample head as the studio loads it: the independent reference for the mesh."""
    return StudioHead.load(SAMPLE)


def _mesh(obj: Any) -> np.ndarray:
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def test_import_head_creates_the_skin_and_every_channel(blender: Any, reference: StudioHead) -> None:
    from studio.blender import scene

    obj = scene.import_head(SAMPLE)
    names = [c.name for c in reference.channels]
    assert all(n in obj for n in names)
    assert sum(n.startswith("arkit.") for n in names) == 52
    assert len(obj.data.vertices) == reference.predictor.n_vertices
    assert np.array_equal(_mesh(obj), reference.predictor.predict(reference.neutral).astype(np.float32))
    ui = obj.id_properties_ui("jaw").as_dict()
    assert ui["min"] == pytest.approx(reference.by_name["jaw"].min) and ui["max"] == pytest.approx(
        reference.by_name["jaw"].max)
    assert obj.modifiers[0].type == "SUBSURF" and obj.data.color_attributes.get(scene.COLOR_ATTR) is not None
    assert obj[scene.PASSES_PROP] and obj[scene.VERDICT_PROP].startswith("Accepted")


def test_set_channels_and_the_mesh_equals_the_predictors_output(blender: Any, reference: StudioHead) -> None:
    from studio.blender import scene

    obj = scene.import_head(SAMPLE)
    obj["jaw"] = 8.0
    obj["blink"] = 12.0
    obj["arkit.mouthSmileLeft"] = 0.6
    blender.context.view_layer.update()  # the depsgraph handler updates the head
    p, _ = reference.solve_targets({"arkit.mouthSmileLeft": 0.6}, reference.neutral)
    p = reference.apply(reference.apply(p, {"blink": 12.0}), {"jaw": 8.0})
    want = reference.predictor.predict(p).astype(np.float32)
    assert np.abs(_mesh(obj) - want).max() == 0.0
    assert np.abs(want - reference.predictor.predict(reference.neutral)).max() > 1e-3  # it did move

    # Animated channels follow the frame (the frame-change handler).
    obj["jaw"] = 0.0
    obj.keyframe_insert('["jaw"]', frame=1)
    obj["jaw"] = 14.0
    obj.keyframe_insert('["jaw"]', frame=21)
    blender.context.scene.frame_set(11)
    jaw = obj["jaw"]
    assert 0.0 < jaw < 14.0
    q = reference.apply(reference.apply(reference.solve_targets({"arkit.mouthSmileLeft": 0.6}, reference.neutral)[0],
                                        {"blink": 12.0}), {"jaw": jaw})
    assert np.abs(_mesh(obj) - reference.predictor.predict(q).astype(np.float32)).max() == 0.0


def test_strain_colours_and_the_guards_verdict_follow_the_pose(blender: Any, reference: StudioHead) -> None:
    from studio.blender import scene

    obj = scene.import_head(SAMPLE)
    colors = np.empty(4 * len(obj.data.vertices), dtype=np.float32)
    obj.data.color_attributes[scene.COLOR_ATTR].data.foreach_get("color", colors)
    rest = colors.reshape(-1, 4).copy()
    obj["jaw"] = 10.0
    obj["arkit.mouthSmileLeft"] = 0.6  # beyond the validated stretch on the sample head
    state, changed = scene.update_head(obj)
    assert changed and not state.passes and not obj[scene.PASSES_PROP]
    assert obj[scene.VERDICT_PROP].startswith("Refused: stretch")
    assert not reference.guard.check(state.pose)
    obj.data.color_attributes[scene.COLOR_ATTR].data.foreach_get("color", colors)
    posed = colors.reshape(-1, 4)
    red = np.array([215, 35, 35]) / 255.0
    assert (np.abs(posed[:, :3] - red ** 2.2).max(axis=1) < 0.05).sum() > 0  # some skin past the limit is red
    assert not np.array_equal(rest, posed)
    # The timeline scan marks the refused frames.
    obj["jaw"] = 0.0
    obj.keyframe_insert('["jaw"]', frame=1)
    obj["jaw"] = 10.0
    obj.keyframe_insert('["jaw"]', frame=10)
    sc = blender.context.scene
    sc.frame_start, sc.frame_end = 1, 10
    refused = scene.scan_guard(sc, obj)
    assert 1 not in refused and 10 in refused
    assert sorted(m.frame for m in sc.timeline_markers if m.name == "refused") == refused


CLIP = {"name": "round", "channels": {
    "jaw": {"interp": "bezier", "keys": [[0.0, 0.0, 0.0, 0.0, 0.21, 3.3],
                                         [0.8123456789, 17.123456789, -0.2, 1.7, 0.3, -2.1],
                                         [61.3, 12.5, -0.4, 0.0, 0.0, 0.0]]},
    "blink": {"interp": "step", "keys": [[0.0, 0.0], [0.4, 40.0], [0.55, 0.0]]},
    "lip_corner_l": {"interp": "linear", "keys": [[0.0, 0.0], [0.3, -33.3333333333], [1.1, 7.0]]},
    "arkit.jawOpen": {"interp": "linear", "keys": [[0.0, 0.0], [0.5, 0.7], [1.0, 0.123456789]]},
}}


def test_clip_to_action_to_clip_reproduces_every_key(blender: Any, tmp_path: Path) -> None:
    from studio.blender import anim, scene

    obj = scene.import_head(SAMPLE)
    sc = blender.context.scene
    sc.render.fps, sc.frame_start = 30, 1
    path = tmp_path / "round.json"
    path.write_text(json.dumps(CLIP))
    assert blender.ops.likeness.import_clip(filepath=str(path)) == {"FINISHED"}
    out_path = tmp_path / "out.json"
    assert blender.ops.likeness.export_clip(filepath=str(out_path)) == {"FINISHED"}
    out = json.loads(out_path.read_text())
    assert set(out["channels"]) == set(CLIP["channels"])
    for ch, spec in CLIP["channels"].items():
        assert out["channels"][ch]["interp"] == spec["interp"]
        assert np.abs(np.array(out["channels"][ch]["keys"]) - np.array(spec["keys"])).max() <= 1e-6, ch

    # Blender evaluates the action as the clip defines it (handles converted, not only stored): within float32.
    want = clip_from_dict(CLIP)
    curves = anim.animated_channels(obj)
    for t in np.linspace(0.0, 1.5, 37):
        frame = 1 + 30 * t
        for ch, fc in curves.items():
            assert fc.evaluate(frame) == pytest.approx(want.channels[ch].value(t), abs=2e-4 * max(1, abs(
                want.channels[ch].value(t)))), (ch, t)

    # A key moved in Blender exports where it now is; the others stay exact.
    kp = curves["lip_corner_l"].keyframe_points[1]
    kp.co = (kp.co[0] + 3.0, -20.0)
    edited = anim.action_to_clip(obj, "edited")["channels"]["lip_corner_l"]["keys"]
    assert edited[0] == [0.0, 0.0] and edited[2] == [1.1, 7.0]
    assert edited[1] == pytest.approx([0.4, -20.0], abs=1e-5)
    # Resampled on request: linear keys at every frame.
    resampled = anim.action_to_clip(obj, "r", channels=["blink"], resample_step=1.0)["channels"]["blink"]
    keys = np.array(resampled["keys"])
    assert resampled["interp"] == "linear" and len(keys) == 18  # frames 0..16 of the clip, then its end at 16.5
    assert keys[-1, 0] == pytest.approx(0.55) and np.allclose(keys[:, 1], [want.channels["blink"].value(t)
                                                                           for t in keys[:, 0]])


def test_a_recording_comes_back_as_an_action(blender: Any, tmp_path: Path) -> None:
    from studio.blender import anim, scene

    obj = scene.import_head(SAMPLE)
    t = np.arange(0, 2.0, 0.004)
    rows = np.column_stack([t + 100.0, 5 * t, np.full_like(t, 2.0), 5 * t - 0.3, np.full_like(t, 2.1)])
    path = write_lrec(tmp_path / "take.lrec", ["jaw", "brow_l"], rows)
    assert blender.ops.likeness.import_clip(filepath=str(path), curves="measured") == {"FINISHED"}
    curves = anim.animated_channels(obj)
    assert set(curves) == {"jaw", "brow_l"} and obj.animation_data.action.name == "take"
    sc = blender.context.scene
    sc.frame_set(sc.frame_start + 24)  # 1 s into the take
    assert obj["jaw"] == pytest.approx(5 * 1.0 - 0.3, abs=1e-3) and obj["brow_l"] == pytest.approx(2.1)


def test_audio_goes_into_the_sequencer_and_the_timeline_syncs_to_it(blender: Any, tmp_path: Path) -> None:
    import wave

    rate, seconds = 22050, 2.5
    t = np.arange(int(rate * seconds)) / rate
    with wave.open(str(tmp_path / "line.wav"), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate)
        w.writeframes((0.5 * np.sin(2 * np.pi * 220 * t) * 32767).astype("<i2").tobytes())
    sc = blender.context.scene
    sc.frame_start, sc.frame_end = 1, 10
    assert blender.ops.likeness.add_audio(filepath=str(tmp_path / "line.wav")) == {"FINISHED"}
    editor = sc.sequence_editor
    strips = [s for s in (editor.strips if hasattr(editor, "strips") else editor.sequences) if s.type == "SOUND"]
    assert [s.name for s in strips] == ["line"]
    fps = sc.render.fps / sc.render.fps_base
    assert strips[0].frame_final_start == 1
    assert strips[0].frame_final_duration == pytest.approx(seconds * fps, abs=1)
    assert sc.frame_end == strips[0].frame_final_end - 1  # the range reaches the sound's end
    assert sc.sync_mode == "AUDIO_SYNC"
    (tmp_path / "noise.wav").write_bytes(b"not a sound")
    with pytest.raises(RuntimeError, match=r"noise\.wav"):
        blender.ops.likeness.add_audio(filepath=str(tmp_path / "noise.wav"))
    with pytest.raises(RuntimeError, match="no such sound file"):
        blender.ops.likeness.add_audio(filepath=str(tmp_path / "missing.wav"))


def test_unknown_channels_and_missing_head_files_are_named(blender: Any) -> None:
    from models.clip import ClipError
    from studio.blender import anim, scene

    obj = scene.import_head(SAMPLE)
    bad = {"name": "bad", "channels": {"nose": {"interp": "linear", "keys": [[0, 0], [1, 1]]}}}
    with pytest.raises(ClipError, match=r"\['nose'\] are not channels of head"):
        anim.clip_to_action(obj, bad, [c.name for c in scene.head_rig(obj).channels])
    # A head whose files moved shows why as its verdict instead of failing every frame.
    obj[scene.HEAD_PROP] = "/nowhere/head.toml"
    assert scene.update_heads(blender.context.scene) == []
    assert obj[scene.VERDICT_PROP].startswith("Cannot show the skin") and "/nowhere/head.toml" in obj[
        scene.VERDICT_PROP]


def test_the_installed_addon_package_registers_in_blender(blender: Any, tmp_path: Path) -> None:
    from studio.blender import addon
    from studio.blender.install import ADDON, install

    addon.unregister()  # the fixture's registration: the installed package registers it again
    folder = install(tmp_path)
    spec = importlib.util.spec_from_file_location(ADDON, folder / "__init__.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.bl_info["blender"] == (4, 2, 0)
    module.register()
    try:
        assert blender.ops.likeness.import_head(filepath=str(SAMPLE)) == {"FINISHED"}
        assert any(o.get("likeness_head") for o in blender.context.scene.objects)
        assert hasattr(blender.types, "LIKENESS_PT_panel")
    finally:
        module.unregister()
        addon.register()  # for the fixture's teardown
