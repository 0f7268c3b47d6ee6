"""Render docs/blender.md's pictures with Blender itself (``bpy``, Workbench, no GPU needed): the sample head
imported by the add-on at rest, posed through ARKit channels, pushed past the guard's range, and three frames of the
sample performance imported as an action. Writes the PNGs and ``blender_screenshots.json`` (each picture's channels,
the guard's verdict, the inputs' hashes and the render settings) into the output folder.

    python -m tools.blender_screenshots                  # into docs/images/
    python -m tools.blender_screenshots --out /tmp/shots
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"
PERFORMANCE = ROOT / "heads" / "sample" / "performances" / "expressive.json"
POSES: dict[str, dict[str, float]] = {
    "blender_rest": {},
    "blender_arkit_smile": {"arkit.mouthSmileLeft": 0.6, "arkit.mouthSmileRight": 0.6, "arkit.jawOpen": 0.2},
    "blender_refused": {"jaw": 10.0, "arkit.mouthSmileLeft": 0.6},
}
CLIP_TIMES = (1.5, 2.5, 3.5)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _stage(bpy: Any, obj: Any, size: tuple[int, int]) -> None:
    """Workbench with the strain colours, a camera in front of the head."""
    import numpy as np

    sc = bpy.context.scene
    sc.render.engine = "BLENDER_WORKBENCH"
    sc.display.shading.light = "STUDIO"
    sc.display.shading.color_type = "VERTEX"
    sc.display.shading.show_specular_highlight = False
    sc.render.resolution_x, sc.render.resolution_y = size
    sc.render.film_transparent = False
    sc.render.dither_intensity = 0.0  # no noise: the PNGs compress to a fraction
    settings = sc.render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth, settings.compression = "PNG", "RGB", "8", 100
    sc.world = sc.world or bpy.data.worlds.new("World")
    sc.world.color = (0.9, 0.9, 0.92)
    bpy.context.view_layer.update()
    corners = np.array([obj.matrix_world @ v.co for v in obj.data.vertices])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    centre = 0.5 * (lo + hi)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.data.lens = 85.0
    sc.collection.objects.link(cam)
    sc.camera = cam
    distance = 2.6 * max(hi[0] - lo[0], hi[2] - lo[2]) * 85.0 / 36.0 / 2.0
    cam.location = (centre[0] + 0.35 * distance, lo[1] - distance, centre[2] + 0.15 * distance)
    direction = centre - np.array(cam.location)
    cam.rotation_euler = _look(direction)


def _look(d: Any) -> tuple[float, float, float]:
    """Euler angles of a camera looking along ``d`` (Blender cameras look down their -z)."""
    import math

    x, y, z = (float(v) for v in d)
    return (math.atan2(math.hypot(x, y), -z), 0.0, math.atan2(y, x) - math.pi / 2)


def render(out: Path, size: tuple[int, int] = (640, 480)) -> dict[str, Any]:
    """Render every picture into ``out``; returns the manifest (also written as blender_screenshots.json)."""
    import bpy

    from studio.blender import addon, anim, scene

    out.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    obj = scene.import_head(SAMPLE)
    _stage(bpy, obj, size)
    sc = bpy.context.scene
    shots: dict[str, Any] = {}

    def shoot(name: str, extra: dict[str, Any]) -> None:
        sc.render.filepath = str(out / f"{name}.png")
        bpy.ops.render.render(write_still=True)
        shots[name] = {"verdict": obj[scene.VERDICT_PROP], "passes": bool(obj[scene.PASSES_PROP]),
                       "utilisation": round(float(obj[scene.UTIL_PROP]), 3), **extra}

    for name, values in POSES.items():
        for ch in scene.head_rig(obj).channels:
            obj[ch.name] = float(ch.neutral)
        for ch, v in values.items():
            obj[ch] = v
        scene.update_head(obj)
        shoot(name, {"channels": values})
    clip = json.loads(PERFORMANCE.read_text())
    sc.render.fps = 24
    anim.clip_to_action(obj, clip, [c.name for c in scene.head_rig(obj).channels])
    for t in CLIP_TIMES:
        frame = round(sc.frame_start + t * 24)
        sc.frame_set(frame)
        shoot(f"blender_clip_{frame:03d}", {"clip": clip["name"], "frame": frame, "time_s": t})
    addon.unregister()
    manifest = {"command": "python -m tools.blender_screenshots", "blender": bpy.app.version_string,
                "engine": "BLENDER_WORKBENCH", "size": list(size), "subdivision": 2,
                "inputs": {str(p.relative_to(ROOT)): _sha(p) for p in (SAMPLE, SAMPLE.parent / "predictor.onnx",
                                                                     SAMPLE.parent / "skin_guard.npz", PERFORMANCE)},
                "shots": shots}
    (out / "blender_screenshots.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "images", help="output folder (default docs/images)")
    args = p.parse_args(argv)
    manifest = render(args.out)
    for name, shot in manifest["shots"].items():
        print(f"{name}.png: {shot['verdict']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
