"""Clip curves ↔ Blender keyframes, without Blender: the exact conversion between the protocol's keys (seconds from
the clip start, Bezier handles as offsets) and Blender's F-curve keys (frames, handles as absolute points).

Blender holds key coordinates in 32-bit floats, so a clip's 64-bit keys cannot survive a trip through an F-curve by
themselves (a value of 40 ° keeps only about 4e-6 °, a time at frame 1500 only about 5e-6 s). Importing therefore also
records each channel's exact keys beside the action (:class:`ExactKeys`); exporting uses a recorded key wherever the
F-curve's key still rounds to it in 32 bits, and the F-curve's own numbers where the animator has moved, added or
edited a key. A clip → action → clip round trip thus reproduces every key exactly.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.clip import ClipError, make_curve

#: Blender's key interpolation for each clip interpolation.
TO_BLENDER = {"step": "CONSTANT", "linear": "LINEAR", "bezier": "BEZIER"}
FROM_BLENDER = {v: k for k, v in TO_BLENDER.items()}

Point = tuple[float, float]


@dataclass(frozen=True)
class Keyframe:
    """One F-curve key as Blender holds it: frame and value, both handles as absolute (frame, value) points, and
    the interpolation of the segment that starts at this key (``CONSTANT``, ``LINEAR``, ``BEZIER``, ...)."""

    frame: float
    value: float
    left: Point
    right: Point
    interpolation: str

    def rounded(self) -> tuple[float, ...]:
        """The key as 32-bit floats (what an F-curve stores), for matching against recorded exact keys."""
        nums = (self.frame, self.value, *self.left, *self.right)
        return tuple(float(x) for x in np.asarray(nums, dtype=np.float32))


@dataclass(frozen=True)
class TimeBase:
    """Clip time ↔ frames: ``frame = frame_start + t * fps``."""

    fps: float
    frame_start: float

    def frame(self, t: float) -> float:
        return self.frame_start + t * self.fps

    def time(self, frame: float) -> float:
        return (frame - self.frame_start) / self.fps


def keyframes_from_channel(spec: Mapping[str, Any], base: TimeBase, where: str = "channel") -> list[Keyframe]:
    """Blender keyframes of one clip channel (``{"interp", "keys"}``, validated by :func:`models.clip.make_curve`)."""
    interp = spec.get("interp", "linear")
    keys = spec.get("keys")
    make_curve(interp, keys, where)  # validates (raises ClipError naming the key)
    blender = TO_BLENDER[interp]
    out = []
    for key in keys:
        t, v = float(key[0]), float(key[1])
        f = base.frame(t)
        if interp == "bezier":
            left = (base.frame(t + float(key[2])), v + float(key[3]))
            right = (base.frame(t + float(key[4])), v + float(key[5]))
        else:
            left = right = (f, v)
        out.append(Keyframe(f, v, left, right, blender))
    return out


def channel_interp(keys: Sequence[Keyframe], where: str) -> str:
    """The clip interpolation of a run of Blender keys (the last key's own interpolation does not matter):
    one kind → that kind; linear and Bezier segments together → ``bezier`` (a linear segment is the Bezier with
    handles at its thirds); anything else (constant beside others, Blender's easing presets) cannot be written
    exactly, so it is a :class:`ClipError` naming the channel and frame (export with resampling instead)."""
    kinds = {k.interpolation for k in keys[:-1]} or {keys[0].interpolation}
    if len(kinds) == 1 and next(iter(kinds)) in FROM_BLENDER:
        return FROM_BLENDER[next(iter(kinds))]
    if kinds <= {"LINEAR", "BEZIER"}:
        return "bezier"
    bad = next(k for k in keys[:-1] if k.interpolation not in ("LINEAR", "BEZIER"))
    raise ClipError(f"{where}: key at frame {bad.frame:g} interpolates {bad.interpolation}, which a clip channel "
                    f"cannot hold beside {sorted(kinds - {bad.interpolation})}; export with resampling")


def channel_from_keyframes(keys: Sequence[Keyframe], base: TimeBase, where: str = "channel",
                           exact: Mapping[tuple[float, ...], Sequence[float]] | None = None) -> dict[str, Any]:
    """One clip channel (``{"interp", "keys"}``) of Blender keys, exactly: each key's handles become offsets;
    a key that still rounds to a recorded exact key (``exact``: :meth:`ExactKeys.lookup`) is written as recorded."""
    if not keys:
        raise ClipError(f"{where}: has no keys")
    interp = channel_interp(keys, where)
    rows: list[list[float]] = []
    for j, k in enumerate(keys):
        rec = exact.get(k.rounded()) if exact else None
        if rec is not None and len(rec) == (6 if interp == "bezier" else 2):
            rows.append([float(x) for x in rec])
            continue
        t = base.time(k.frame)
        if interp != "bezier":
            rows.append([t, k.value])
            continue
        left, right = k.left, k.right
        if k.interpolation == "LINEAR" and j + 1 < len(keys):  # straight segment: handles at the thirds
            nxt = keys[j + 1]
            right = (k.frame + (nxt.frame - k.frame) / 3, k.value + (nxt.value - k.value) / 3)
        if j > 0 and keys[j - 1].interpolation == "LINEAR":
            prv = keys[j - 1]
            left = (k.frame - (k.frame - prv.frame) / 3, k.value - (k.value - prv.value) / 3)
        in_dt, out_dt = base.time(left[0]) - t, base.time(right[0]) - t
        if in_dt > 0 or out_dt < 0:
            raise ClipError(f"{where}: key at frame {k.frame:g} has a handle on the wrong side of the key "
                            f"(left at frame {left[0]:g}, right at {right[0]:g})")
        rows.append([t, k.value, in_dt, left[1] - k.value, out_dt, right[1] - k.value])
    make_curve(interp, rows, where)  # what we write must read back
    return {"interp": interp, "keys": rows}


@dataclass
class ExactKeys:
    """The exact (64-bit) keys of the clip an action was imported from, by channel, with the time base they were
    converted with; stored beside the action as JSON (:meth:`to_json`)."""

    base: TimeBase
    channels: dict[str, list[tuple[tuple[float, ...], list[float]]]]

    @classmethod
    def of_clip(cls, clip: Mapping[str, Any], base: TimeBase) -> ExactKeys:
        """Record every key of a clip map, each beside its 32-bit Blender form."""
        out: dict[str, list[tuple[tuple[float, ...], list[float]]]] = {}
        for ch, spec in clip["channels"].items():
            kfs = keyframes_from_channel(spec, base, f"clip.channels.{ch}")
            out[ch] = [(k.rounded(), [float(x) for x in key]) for k, key in zip(kfs, spec["keys"], strict=True)]
        return cls(base, out)

    def lookup(self, channel: str, base: TimeBase) -> dict[tuple[float, ...], list[float]]:
        """Rounded key → exact key for one channel; empty when the scene's time base has changed since."""
        if base != self.base:
            return {}
        return {r: k for r, k in self.channels.get(channel, [])}

    def to_json(self) -> dict[str, Any]:
        return {"fps": self.base.fps, "frame_start": self.base.frame_start,
                "channels": {ch: [[list(r), k] for r, k in rows] for ch, rows in self.channels.items()}}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ExactKeys:
        base = TimeBase(float(data["fps"]), float(data["frame_start"]))
        chans = {ch: [(tuple(float(x) for x in r), [float(x) for x in k]) for r, k in rows]
                 for ch, rows in data["channels"].items()}
        return cls(base, chans)
