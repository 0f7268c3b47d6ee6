"""Actions ↔ clips inside Blender: a head object's action (its channel properties' F-curves) exported as the
protocol's clip map, exactly or resampled on request, and a clip (or a recording) imported as an action.

Blender 4.4+ actions are layered: the F-curves of an object live in the channel bag of its slot in the action's
keyframe strip; Blender 4.2/4.3 keep them on ``action.fcurves``. :func:`fcurves` hides the difference.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from typing import Any

import bpy
import numpy as np

from models.clip import ClipError, clip_from_dict
from studio.blender.curves import ExactKeys, Keyframe, TimeBase, channel_from_keyframes, keyframes_from_channel

#: Custom property of an action holding the exact keys of the clip it was imported from.
EXACT_PROP = "likeness_exact"
_PATH = re.compile(r'^\["((?:[^"\\]|\\.)*)"\]$')


def time_base(scene: bpy.types.Scene) -> TimeBase:
    """The scene's frame rate and start frame: clip time 0 is ``frame_start``."""
    return TimeBase(scene.render.fps / scene.render.fps_base, float(scene.frame_start))


def channel_path(name: str) -> str:
    """The F-curve data path of a channel property."""
    return '["' + name.replace("\\", "\\\\").replace('"', '\\"') + '"]'


def path_channel(path: str) -> str | None:
    """The channel property a data path animates (None for anything else)."""
    m = _PATH.match(path)
    return None if m is None else re.sub(r"\\(.)", r"\1", m.group(1))


def fcurves(obj: bpy.types.Object, create: bool = False) -> Any:
    """The F-curve collection of the object's action (None without one, unless ``create``)."""
    ad = obj.animation_data
    if ad is None or ad.action is None:
        if not create:
            return None
        ad = ad or obj.animation_data_create()
        ad.action = bpy.data.actions.new(f"{obj.name}Action")
    action = ad.action
    if not hasattr(action, "layers"):  # Blender 4.2/4.3
        return action.fcurves
    from bpy_extras import anim_utils

    slot = ad.action_slot
    if slot is None:
        if not create:
            return None
        slot = action.slots.new(id_type="OBJECT", name=obj.name)
        ad.action_slot = slot
    if create:
        return anim_utils.action_ensure_channelbag_for_slot(action, slot).fcurves
    bag = anim_utils.action_get_channelbag_for_slot(action, slot)
    return None if bag is None else bag.fcurves


def animated_channels(obj: bpy.types.Object) -> dict[str, Any]:
    """Channel name → its F-curve, for the object's animated channel properties."""
    curves = fcurves(obj)
    if curves is None:
        return {}
    out = {}
    for fc in curves:
        name = path_channel(fc.data_path)
        if name is not None and len(fc.keyframe_points):
            out[name] = fc
    return out


def read_keyframes(fc: Any) -> list[Keyframe]:
    """An F-curve's keys as :class:`Keyframe` (32-bit numbers widened exactly)."""
    n = len(fc.keyframe_points)
    arrays = {}
    for attr in ("co", "handle_left", "handle_right"):
        a = np.empty(2 * n, dtype=np.float32)
        fc.keyframe_points.foreach_get(attr, a)
        arrays[attr] = a.reshape(n, 2).astype(np.float64)
    out = []
    for j, kp in enumerate(fc.keyframe_points):
        co, hl, hr = arrays["co"][j], arrays["handle_left"][j], arrays["handle_right"][j]
        out.append(Keyframe(float(co[0]), float(co[1]), (float(hl[0]), float(hl[1])), (float(hr[0]), float(hr[1])),
                            kp.interpolation))
    return out


def write_keyframes(fc: Any, keys: list[Keyframe]) -> None:
    """Replace an F-curve's keys; handles are FREE, so Blender keeps them as given."""
    fc.keyframe_points.clear()
    fc.keyframe_points.add(len(keys))
    for kp, k in zip(fc.keyframe_points, keys, strict=True):
        kp.handle_left_type = kp.handle_right_type = "FREE"
        kp.interpolation = k.interpolation
    for attr, rows in (("co", [(k.frame, k.value) for k in keys]), ("handle_left", [k.left for k in keys]),
                       ("handle_right", [k.right for k in keys])):
        fc.keyframe_points.foreach_set(attr, np.asarray(rows, dtype=np.float32).ravel())
    fc.update()


def exact_keys(obj: bpy.types.Object) -> ExactKeys | None:
    ad = obj.animation_data
    raw = ad.action.get(EXACT_PROP) if ad is not None and ad.action is not None else None
    return ExactKeys.from_json(json.loads(raw)) if isinstance(raw, str) else None


def action_to_clip(obj: bpy.types.Object, name: str, channels: Iterable[str] | None = None,
                   resample_step: float | None = None) -> dict[str, Any]:
    """The clip map of the object's animated channels (``channels``: a subset). Exact keys and handles by default;
    with ``resample_step`` (frames) every channel is sampled into linear keys at that step over its keyed range."""
    scene = obj.users_scene[0] if obj.users_scene else bpy.context.scene
    base = time_base(scene)
    curves = animated_channels(obj)
    wanted = list(curves) if channels is None else list(channels)
    missing = [c for c in wanted if c not in curves]
    if missing:
        raise ClipError(f"{obj.name}: channel(s) {missing} are not animated (animated: {sorted(curves)})")
    if not wanted:
        raise ClipError(f"{obj.name}: no animated channel to export (key a channel property first)")
    exact = exact_keys(obj)
    out: dict[str, Any] = {}
    for ch in wanted:
        fc = curves[ch]
        where = f"{obj.name}.{ch}"
        if resample_step is None:
            lookup = exact.lookup(ch, base) if exact is not None else None
            out[ch] = channel_from_keyframes(read_keyframes(fc), base, where, lookup)
            continue
        lo, hi = fc.range()
        frames = np.append(np.arange(lo, hi, resample_step), hi)
        frames = frames[np.r_[True, np.diff(frames) > 1e-9]]
        out[ch] = {"interp": "linear", "keys": [[base.time(float(f)), float(fc.evaluate(f))] for f in frames]}
    clip = {"name": name, "channels": out}
    clip_from_dict(clip, where=f"{obj.name} export")
    return clip


def clip_to_action(obj: bpy.types.Object, clip: Mapping[str, Any], known: Iterable[str]) -> Any:
    """A new action on the object holding the clip's channels (each a channel property in ``known``), its exact
    keys recorded beside it; returns the action. The scene's frame range is widened to the clip."""
    clip_from_dict(clip, where=f"clip {clip.get('name')!r}")
    names = set(known)
    unknown = sorted(set(clip["channels"]) - names)
    if unknown:
        raise ClipError(f"clip {clip['name']!r}: channel(s) {unknown} are not channels of head {obj.name!r}")
    scene = obj.users_scene[0] if obj.users_scene else bpy.context.scene
    base = time_base(scene)
    ad = obj.animation_data or obj.animation_data_create()
    ad.action = bpy.data.actions.new(str(clip["name"]))
    curves = fcurves(obj, create=True)
    end = base.frame_start
    exact = ExactKeys(base, {})
    for ch, spec in clip["channels"].items():
        keys = keyframes_from_channel(spec, base, f"clip {clip['name']!r}.channels.{ch}")
        fc = curves.new(channel_path(ch))
        write_keyframes(fc, keys)
        end = max(end, keys[-1].frame)
        # Recorded beside the numbers Blender stored (it nudges zero-length handles off their key).
        stored = read_keyframes(fc)
        exact.channels[ch] = [(k.rounded(), [float(x) for x in key]) for k, key in zip(stored, spec["keys"],
                                                                                        strict=True)]
    ad.action[EXACT_PROP] = json.dumps(exact.to_json())
    scene.frame_end = max(scene.frame_end, int(np.ceil(end)))
    return ad.action
