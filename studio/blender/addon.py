"""The add-on's Blender side: operators (import a head, export and import clips and recordings, scan the guard over
the frame range, the live link and its E-stop), the sidebar panel, and the handlers that keep every head's skin
in step with its channels and the timeline and stream the shown frames while the live link is on.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from models.atomic import write_text
from models.client import DaemonError
from models.clip import ClipError, clip_file_as_dict
from models.errors import LikenessError
from studio.blender import anim, audio, scene
from studio.blender.live import LiveLink
from studio.blender.recording import recording_clip

SAMPLE_HEAD = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


class _State:
    """The live link of this Blender session (one at a time) and the head it streams."""

    link: LiveLink | None = None
    head: str = ""


def link() -> LiveLink | None:
    return _State.link


def _active_head(context: Any) -> Any:
    obj = context.active_object
    if scene.is_head(obj):
        return obj
    return next((o for o in context.scene.objects if scene.is_head(o)), None)


def _stream(sc: Any, obj: Any, state: Any) -> None:
    lk = _State.link
    if lk is None or obj.name != _State.head:
        return
    fps = sc.render.fps / sc.render.fps_base
    lk.frame(sc.frame_current + sc.frame_subframe, fps, scene.head_rig(obj).channel_values(state.pose))


@persistent
def on_frame_change(sc: Any, depsgraph: Any = None) -> None:
    """After the timeline moves (playing or scrubbing): update every head, stream the linked one."""
    for obj, state, _changed in scene.update_heads(sc):
        _stream(sc, obj, state)


@persistent
def on_depsgraph_update(sc: Any, depsgraph: Any = None) -> None:
    """After an edit (a channel slider, a key moved): update heads whose channels changed; stream a changed pose."""
    for obj, state, changed in scene.update_heads(sc):
        if changed:
            _stream(sc, obj, state)


class LIKENESS_OT_import_head(bpy.types.Operator, ImportHelper):
    """Import a Likeness head (head.toml): the predicted skin as a mesh with every channel as a property"""

    bl_idname = "likeness.import_head"
    bl_label = "Import Likeness Head"
    bl_options: ClassVar[set[str]] = {"REGISTER", "UNDO"}
    filename_ext = ".toml"
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})  # type: ignore[valid-type]

    def execute(self, context: Any) -> set[str]:
        try:
            obj = scene.import_head(self.filepath or SAMPLE_HEAD, context.scene)
        except (LikenessError, ValueError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        context.view_layer.objects.active = obj
        return {"FINISHED"}


class LIKENESS_OT_export_clip(bpy.types.Operator, ExportHelper):
    """Export the head's action as a Likeness clip (JSON): keys and Bezier handles exactly, or resampled"""

    bl_idname = "likeness.export_clip"
    bl_label = "Export Likeness Clip"
    filename_ext = ".json"
    resample: BoolProperty(name="Resample", default=False,  # type: ignore[valid-type]
                           description="Sample every channel into linear keys (for easing presets and mixed keys)")
    step: FloatProperty(name="Step (frames)", default=1.0, min=0.01)  # type: ignore[valid-type]

    def execute(self, context: Any) -> set[str]:
        obj = _active_head(context)
        if obj is None:
            self.report({"ERROR"}, "no Likeness head in the scene")
            return {"CANCELLED"}
        try:
            clip = anim.action_to_clip(obj, Path(self.filepath).stem or "clip",
                                       resample_step=self.step if self.resample else None)
        except ClipError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        write_text(self.filepath, json.dumps(clip, indent=1) + "\n")
        self.report({"INFO"}, f"wrote {len(clip['channels'])} channels to {self.filepath}")
        return {"FINISHED"}


class LIKENESS_OT_import_clip(bpy.types.Operator, ImportHelper):
    """Import a Likeness clip (.json, .csv) or a daemon recording (.lrec, .npz) as the head's action"""

    bl_idname = "likeness.import_clip"
    bl_label = "Import Likeness Clip or Recording"
    bl_options: ClassVar[set[str]] = {"REGISTER", "UNDO"}
    filter_glob: StringProperty(default="*.json;*.csv;*.lrec;*.npz", options={"HIDDEN"})  # type: ignore[valid-type]
    curves: EnumProperty(name="Recording curves", default="commanded",  # type: ignore[valid-type]
                         items=[("commanded", "Commanded", ""), ("measured", "Measured", "")])

    def execute(self, context: Any) -> set[str]:
        obj = _active_head(context)
        if obj is None:
            self.report({"ERROR"}, "no Likeness head in the scene: import a head first")
            return {"CANCELLED"}
        path = Path(self.filepath)
        try:
            if path.suffix.lower() in (".lrec", ".npz"):
                clip = recording_clip(path, self.curves)
            else:
                clip = clip_file_as_dict(path)
            anim.clip_to_action(obj, clip, [c.name for c in scene.head_rig(obj).channels])
        except (LikenessError, ClipError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class LIKENESS_OT_scan_guard(bpy.types.Operator):
    """Mark every frame whose pose the strain guard refuses on the timeline ('refused' markers)"""

    bl_idname = "likeness.scan_guard"
    bl_label = "Mark Refused Frames"

    def execute(self, context: Any) -> set[str]:
        obj = _active_head(context)
        if obj is None:
            self.report({"ERROR"}, "no Likeness head in the scene")
            return {"CANCELLED"}
        refused = scene.scan_guard(context.scene, obj)
        self.report({"INFO"}, f"{len(refused)} refused frame(s)")
        return {"FINISHED"}


class LIKENESS_OT_live_connect(bpy.types.Operator):
    """Connect to a running daemon and stream the head's shown frames to it while the timeline plays or scrubs"""

    bl_idname = "likeness.live_connect"
    bl_label = "Connect Live"

    def execute(self, context: Any) -> set[str]:
        obj = _active_head(context)
        if obj is None:
            self.report({"ERROR"}, "no Likeness head in the scene")
            return {"CANCELLED"}
        try:
            start_link(obj, context.scene.likeness_endpoint, context.scene.likeness_lead,
                       enable=context.scene.likeness_enable)
        except (LikenessError, DaemonError, ValueError, TimeoutError, OSError) as exc:
            self.report({"ERROR"}, f"live link: {exc}")
            return {"CANCELLED"}
        return {"FINISHED"}


class LIKENESS_OT_live_disconnect(bpy.types.Operator):
    """Stop streaming (the daemon holds, then eases to neutral by its watchdog)"""

    bl_idname = "likeness.live_disconnect"
    bl_label = "Disconnect Live"

    def execute(self, context: Any) -> set[str]:
        stop_link()
        return {"FINISHED"}


class LIKENESS_OT_add_audio(bpy.types.Operator, ImportHelper):
    """Add a sound file (WAV, MP3, ...) to the sequencer at the first frame, played with the timeline"""

    bl_idname = "likeness.add_audio"
    bl_label = "Add Audio"
    filter_glob: StringProperty(default="*.wav;*.mp3;*.ogg;*.flac;*.aac;*.m4a", options={"HIDDEN"})  # type: ignore[valid-type]

    def execute(self, context: Any) -> set[str]:
        try:
            strip = audio.add_sound(context.scene, self.filepath)
        except LikenessError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"{strip.name}: frames {strip.frame_final_start}–{strip.frame_final_end - 1}, "
                              f"timeline synced to audio")
        return {"FINISHED"}


class LIKENESS_OT_estop(bpy.types.Operator):
    """E-stop: latch the daemon's e-stop now, on a socket of its own"""

    bl_idname = "likeness.estop"
    bl_label = "E-STOP"

    def execute(self, context: Any) -> set[str]:
        lk = _State.link
        try:
            if lk is not None:
                lk.estop("Blender E-stop")
            else:
                from models.client import Client

                with Client(context.scene.likeness_endpoint, timeout=1.0) as c:
                    c.call("estop", reason="Blender E-stop")
        except Exception as exc:  # the operator must report any failure to stop, whatever it is
            self.report({"ERROR"}, f"E-stop NOT confirmed: {exc}")
            return {"CANCELLED"}
        self.report({"WARNING"}, "E-stop latched: reset on the daemon before moving again")
        return {"FINISHED"}


def start_link(obj: Any, endpoint: str, lead: float = 0.08, enable: bool = False) -> LiveLink:
    """Start streaming ``obj``'s frames to the daemon at ``endpoint`` (replacing a running link)."""
    stop_link()
    lk = LiveLink(endpoint, scene.head_rig(obj).head.names, lead=lead)
    if enable and lk.call("status")["lifecycle"] == "inactive":
        lk.call("enable", timeout=30)
    _State.link, _State.head = lk, obj.name
    return lk


def stop_link() -> None:
    if _State.link is not None:
        _State.link.close()
    _State.link, _State.head = None, ""


class LIKENESS_PT_panel(bpy.types.Panel):
    """The sidebar's Likeness tab: the guard's verdict of the shown frame, clips, the live link and the E-stop."""

    bl_label = "Likeness"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Likeness"

    def draw(self, context: Any) -> None:
        col = self.layout.column()
        obj = _active_head(context)
        col.operator(LIKENESS_OT_import_head.bl_idname, icon="IMPORT")
        if obj is not None:
            box = col.box()
            ok = bool(obj.get(scene.PASSES_PROP, True))
            box.label(text="Guard: accepted" if ok else "Guard: REFUSED", icon="CHECKMARK" if ok else "ERROR")
            box.label(text=f"strain utilisation {float(obj.get(scene.UTIL_PROP, 0.0)):.2f} (1 = limit)")
            for part in str(obj.get(scene.VERDICT_PROP, "")).split(". "):
                box.label(text=part)
            col.operator(LIKENESS_OT_scan_guard.bl_idname, icon="MARKER_HLT")
            col.operator(LIKENESS_OT_import_clip.bl_idname, icon="ANIM")
            col.operator(LIKENESS_OT_export_clip.bl_idname, icon="EXPORT")
        col.operator(LIKENESS_OT_add_audio.bl_idname, icon="SOUND")
        live = col.box()
        live.prop(context.scene, "likeness_endpoint")
        live.prop(context.scene, "likeness_lead")
        live.prop(context.scene, "likeness_enable")
        lk = _State.link
        if lk is None:
            live.operator(LIKENESS_OT_live_connect.bl_idname, icon="LINKED")
        else:
            live.label(text=f"streaming {lk.stats.frames} frames, late {lk.stats.late}, refused {lk.stats.refused}")
            live.operator(LIKENESS_OT_live_disconnect.bl_idname, icon="UNLINKED")
        stop = col.row()
        stop.scale_y = 2.0
        stop.alert = True
        stop.operator(LIKENESS_OT_estop.bl_idname, icon="CANCEL")


def _menu_import(self: Any, context: Any) -> None:
    self.layout.operator(LIKENESS_OT_import_head.bl_idname, text="Likeness Head (.toml)")
    self.layout.operator(LIKENESS_OT_import_clip.bl_idname, text="Likeness Clip or Recording")


def _menu_export(self: Any, context: Any) -> None:
    self.layout.operator(LIKENESS_OT_export_clip.bl_idname, text="Likeness Clip (.json)")


CLASSES = (LIKENESS_OT_import_head, LIKENESS_OT_export_clip, LIKENESS_OT_import_clip, LIKENESS_OT_scan_guard,
           LIKENESS_OT_live_connect, LIKENESS_OT_live_disconnect, LIKENESS_OT_estop, LIKENESS_OT_add_audio,
           LIKENESS_PT_panel)
HANDLERS = ((bpy.app.handlers.frame_change_post, on_frame_change),
            (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update))


def register() -> None:
    """Register the operators, panel, scene settings and handlers."""
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.likeness_endpoint = StringProperty(name="Daemon", default="tcp://127.0.0.1:5555")
    bpy.types.Scene.likeness_lead = FloatProperty(name="Lead (s)", default=0.08, min=0.0, max=2.0,
                                                  description="How far ahead of now the shown frame is stamped")
    bpy.types.Scene.likeness_enable = BoolProperty(name="Enable head on connect", default=False)
    for handlers, fn in HANDLERS:
        if fn not in handlers:
            handlers.append(fn)
    bpy.types.TOPBAR_MT_file_import.append(_menu_import)
    bpy.types.TOPBAR_MT_file_export.append(_menu_export)


def unregister() -> None:
    """Undo :func:`register` (stopping a running live link)."""
    stop_link()
    bpy.types.TOPBAR_MT_file_import.remove(_menu_import)
    bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
    for handlers, fn in HANDLERS:
        if fn in handlers:
            handlers.remove(fn)
    for name in ("likeness_endpoint", "likeness_lead", "likeness_enable"):
        if hasattr(bpy.types.Scene, name):
            delattr(bpy.types.Scene, name)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
