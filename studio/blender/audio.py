"""Dialogue and music for the animator: a sound file as a strip in Blender's sequencer, played with the timeline.

Blender plays sound strips while its timeline plays; with the scene synced to audio, it drops frames to keep the
picture (and so the frames the live link streams, stamped from the timeline) on the sound's clock.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import bpy

from models.errors import LikenessError


def add_sound(scene: Any, path: str | Path, frame_start: int | None = None, channel: int = 1) -> Any:
    """Add ``path`` as a sound strip at ``frame_start`` (default: the scene's first frame), sync the scene to audio,
    and extend the frame range to the sound's end; the strip. A missing or undecodable file is a LikenessError."""
    p = Path(path)
    if not p.is_file():
        raise LikenessError(f"{p}: no such sound file")
    editor = scene.sequence_editor or scene.sequence_editor_create()
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences  # Blender 4.4+ / before
    start = scene.frame_start if frame_start is None else int(frame_start)
    try:
        strip = strips.new_sound(p.stem, str(p), channel, start)
    except RuntimeError as exc:
        raise LikenessError(f"{p}: Blender cannot read it as sound ({exc})") from exc
    sound = strip.sound
    if sound is None or sound.channels == "INVALID" or sound.samplerate <= 0:
        strips.remove(strip)
        if sound is not None and sound.users == 0:
            bpy.data.sounds.remove(sound)
        raise LikenessError(f"{p}: Blender cannot read it as sound")
    scene.sync_mode = "AUDIO_SYNC"
    scene.frame_end = max(scene.frame_end, strip.frame_final_end - 1)
    return strip
