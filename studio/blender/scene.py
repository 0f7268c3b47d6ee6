"""The head inside Blender: an object whose mesh is the predicted skin surface and whose custom properties are the
head's channels (actuators, groups, the 52 ARKit weights), animatable like any property; :func:`update_head` sets
the mesh, its strain colours and the guard's verdict from the present channel values (the add-on's frame-change and
depsgraph handlers call it). A Subdivision Surface modifier shows the simulated surface smooth; the colours are a
point-domain attribute, so they are interpolated across the surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from models.errors import LikenessError
from studio.blender.anim import animated_channels
from studio.blender.rig import HeadRig, SkinState

#: Object properties the add-on owns (besides one property per channel).
HEAD_PROP = "likeness_head"
VERDICT_PROP = "likeness_verdict"
PASSES_PROP = "likeness_passes"
UTIL_PROP = "likeness_utilisation"
COLOR_ATTR = "likeness_strain"

_RIGS: dict[str, HeadRig] = {}


@dataclass
class _Shown:
    key: tuple[tuple[str, float], ...]
    state: SkinState


_SHOWN: dict[int, _Shown] = {}  # object (session id) → what its mesh shows


def rig_for(config: str | Path) -> HeadRig:
    """The head's rig, loaded once per Blender session (predictor, guard, target solver)."""
    key = str(Path(config).resolve())
    if key not in _RIGS:
        _RIGS[key] = HeadRig.load(key)
    return _RIGS[key]


def is_head(obj: bpy.types.Object | None) -> bool:
    return obj is not None and obj.type == "MESH" and isinstance(obj.get(HEAD_PROP), str)


def head_rig(obj: bpy.types.Object) -> HeadRig:
    return rig_for(obj[HEAD_PROP])


def import_head(config: str | Path, scene: bpy.types.Scene | None = None, name: str | None = None,
                subdivision: int = 2) -> bpy.types.Object:
    """Create the head's object in ``scene``: the skin mesh at rest, a property per channel, the strain colour
    attribute and a material showing it, and (``subdivision`` > 0) a Subdivision Surface modifier."""
    scene = scene or bpy.context.scene
    rig = rig_for(config)
    spec = rig.head.spec
    mesh = bpy.data.meshes.new(f"{name or spec.name}_skin")
    mesh.from_pydata(rig.rest.astype(np.float64).tolist(), [], rig.faces.tolist())
    mesh.validate()
    mesh.polygons.foreach_set("use_smooth", np.ones(len(mesh.polygons), dtype=bool))
    mesh.color_attributes.new(COLOR_ATTR, "FLOAT_COLOR", "POINT")
    mesh.attributes.active_color_name = COLOR_ATTR
    obj = bpy.data.objects.new(name or spec.name, mesh)
    obj.rotation_euler = (np.pi / 2, 0.0, 0.0)  # the head's y-up frame in Blender's z-up world, facing -y (front)
    scene.collection.objects.link(obj)
    obj[HEAD_PROP] = str(Path(config).resolve())
    for ch in rig.channels:
        obj[ch.name] = float(ch.neutral)
        ui = obj.id_properties_ui(ch.name)
        ui.update(min=float(ch.min), max=float(ch.max), soft_min=float(ch.min), soft_max=float(ch.max),
                  default=float(ch.neutral), description=f"{ch.kind} channel, {ch.unit}")
    obj[VERDICT_PROP] = ""
    obj[PASSES_PROP] = True
    obj[UTIL_PROP] = 0.0
    mesh.materials.append(_strain_material())
    if subdivision > 0:
        mod = obj.modifiers.new("Smooth skin", "SUBSURF")
        mod.levels = mod.render_levels = subdivision
    update_head(obj, force=True)
    return obj


def _strain_material() -> bpy.types.Material:
    """A material whose base colour is the strain attribute (Cycles and EEVEE; Workbench shows the attribute)."""
    mat = bpy.data.materials.get("Likeness strain") or bpy.data.materials.new("Likeness strain")
    if bpy.app.version < (5, 0, 0):  # always true from Blender 5 on (the property is deprecated there)
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None) or nodes.new("ShaderNodeBsdfPrincipled")
    attr = nodes.get("Strain") or nodes.new("ShaderNodeAttribute")
    attr.name = "Strain"
    attr.attribute_name = COLOR_ATTR
    mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.55
    return mat


def addressed_values(obj: bpy.types.Object, rig: HeadRig) -> dict[str, float]:
    """The channels that address the head now (animated, or set away from their rest value) and their values."""
    animated = animated_channels(obj)
    out = {}
    for ch in rig.channels:
        value = float(obj.get(ch.name, ch.neutral))
        if ch.name in animated or abs(value - ch.neutral) > 1e-9:
            out[ch.name] = value
    return out


def update_head(obj: bpy.types.Object, force: bool = False) -> tuple[SkinState, bool]:
    """Show the skin of the object's present channel values (mesh, colours, verdict); returns the state and whether
    the mesh changed (unchanged values are not recomputed, which also ends the depsgraph update it causes)."""
    rig = head_rig(obj)
    values = addressed_values(obj, rig)
    key = tuple(sorted((n, v) for n, v in values.items()))
    shown = _SHOWN.get(obj.session_uid)
    if shown is not None and shown.key == key and not force:
        return shown.state, False
    state = rig.skin(rig.pose(values))
    mesh = obj.data
    mesh.vertices.foreach_set("co", state.positions.ravel())
    attr = mesh.color_attributes.get(COLOR_ATTR)
    if attr is not None:
        attr.data.foreach_set("color", state.colors.ravel())
    mesh.update()
    if obj.get(VERDICT_PROP) != state.verdict:
        obj[VERDICT_PROP] = state.verdict
    if obj.get(PASSES_PROP) != state.passes:
        obj[PASSES_PROP] = state.passes
    obj[UTIL_PROP] = state.utilisation
    _SHOWN[obj.session_uid] = _Shown(key, state)
    return state, True


def update_heads(scene: bpy.types.Scene) -> list[tuple[bpy.types.Object, SkinState, bool]]:
    """Update every head object of the scene. A head that cannot be shown (its files moved, a channel property
    deleted) shows the reason as its verdict, once, instead of failing every frame."""
    out = []
    for obj in scene.objects:
        if not is_head(obj):
            continue
        try:
            out.append((obj, *update_head(obj)))
        except (LikenessError, ValueError, KeyError, OSError) as exc:
            reason = f"Cannot show the skin: {exc}"
            if obj.get(VERDICT_PROP) != reason:
                obj[VERDICT_PROP] = reason
                obj[PASSES_PROP] = False
    return out


def scan_guard(scene: bpy.types.Scene, obj: bpy.types.Object, marker: str = "refused") -> list[int]:
    """Frames of the scene's range whose pose the guard refuses, each marked on the timeline (old marks replaced)."""
    for m in [m for m in scene.timeline_markers if m.name == marker]:
        scene.timeline_markers.remove(m)
    rig = head_rig(obj)
    current = scene.frame_current
    refused = []
    for f in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(f)
        if not rig.head.guard.check(rig.pose(addressed_values(obj, rig))):
            refused.append(f)
            scene.timeline_markers.new(marker, frame=f)
    scene.frame_set(current)
    return refused
