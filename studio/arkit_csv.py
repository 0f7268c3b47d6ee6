"""ARKit blendshape recordings as clips: the CSV layout of Live Link Face exports → a clip of ``arkit.*`` channels.

A Live Link Face CSV has a header row ``Timecode,BlendShapeCount,EyeBlinkLeft,...`` (the 52 ARKit blendshape names,
capitalised), optionally followed by head and eye rotation columns (ignored), and one row per captured frame.
``Timecode`` is ``HH:MM:SS:FF.fff`` (frames at the capture rate, with a sub-frame fraction) or plain seconds.
Each blendshape column becomes the linear channel ``arkit.<name>`` (ARKit's own spelling, e.g. ``arkit.jawOpen``)
starting at clip time 0; keys that linear interpolation reproduces within ``tolerance`` are dropped, and channels
that never leave zero are left out.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable

from studio.clipdoc import ClipDoc, ClipError, Key, Track

#: The 52 ARKit blendshapes (ARFaceAnchor.BlendShapeLocation raw values).
ARKIT_BLENDSHAPES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
    "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
    "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)
_BY_LOWER = {n.lower(): n for n in ARKIT_BLENDSHAPES}


def parse_timecode(text: str, fps: float, where: str) -> float:
    """Seconds of a ``HH:MM:SS:FF[.fff]`` timecode at ``fps`` frames per second, or of plain seconds."""
    cell = text.strip()
    parts = cell.split(":")
    try:
        if len(parts) == 1:
            value = float(cell)
        elif len(parts) == 4:
            h, m, s = int(parts[0]), int(parts[1]), int(parts[2])
            frames = float(parts[3])
            if not (0 <= m < 60 and 0 <= s < 60 and 0 <= frames < fps + 1):
                raise ValueError("field out of range")
            value = h * 3600.0 + m * 60.0 + s + frames / fps
        else:
            raise ValueError("expected HH:MM:SS:FF.fff")
    except ValueError as exc:
        raise ClipError(f"{where}: bad timecode {cell!r} ({exc})") from None
    if not math.isfinite(value):
        raise ClipError(f"{where}: bad timecode {cell!r}")
    return value


def reduce_keys(times: list[float], values: list[float], tolerance: float) -> list[int]:
    """Indices of the keys to keep so that linear interpolation of the kept keys stays within ``tolerance`` of
    every dropped one (greedy: extend each segment while it still fits)."""
    n = len(times)
    if n <= 2:
        return list(range(n))
    keep = [0]
    a = 0
    b = 2
    while b < n:
        ta, va, tb, vb = times[a], values[a], times[b], values[b]
        fits = all(abs(va + (vb - va) * (times[j] - ta) / (tb - ta) - values[j]) <= tolerance for j in range(a + 1, b))
        if fits:
            b += 1
            continue
        a = b - 1
        keep.append(a)
        b = a + 2
    keep.append(n - 1)
    return keep


def clip_from_live_link_csv(text: str, name: str, fps: float = 60.0, tolerance: float = 0.002,
                            channels: Iterable[str] | None = None, source: str = "<csv>") -> ClipDoc:
    """A clip of ``arkit.*`` channels from a Live Link Face CSV export.

    ``fps``: the capture rate that the timecode's frame field counts (Live Link Face records at 60 by default).
    ``channels``: the target channels the head serves (others are left out); None keeps every blendshape.
    """
    if not fps > 0:
        raise ClipError(f"{source}: fps must be positive, got {fps!r}")
    rows = list(csv.reader(io.StringIO(text.lstrip("\ufeff"))))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows:
        raise ClipError(f"{source}: empty file")
    header = [h.strip() for h in rows[0]]
    if not header or header[0].lower() != "timecode":
        raise ClipError(f"{source}: row 1 column 1 must be 'Timecode' (the Live Link Face layout), got "
                        f"{header[0] if header else ''!r}")
    columns = {}
    for i, h in enumerate(header):
        shape = _BY_LOWER.get(h.lower())
        if shape is not None:
            columns[shape] = i
    missing = [n for n in ARKIT_BLENDSHAPES if n not in columns]
    if missing:
        raise ClipError(f"{source}: row 1 lacks {len(missing)} of the 52 ARKit blendshape columns: "
                        f"{', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''}")
    wanted = None if channels is None else set(channels)
    times: list[float] = []
    series: dict[str, list[float]] = {n: [] for n in columns}
    for r, row in enumerate(rows[1:], start=2):
        if len(row) < len(header):
            raise ClipError(f"{source}: row {r} has {len(row)} cells, the header {len(header)}")
        t = parse_timecode(row[0], fps, f"{source}: row {r}")
        if times and t <= times[-1]:
            raise ClipError(f"{source}: row {r}: timecode {row[0].strip()!r} does not advance")
        times.append(t)
        for shape, i in columns.items():
            try:
                v = float(row[i])
            except ValueError:
                raise ClipError(f"{source}: row {r}, column {header[i]!r}: not a number ({row[i]!r})") from None
            if not math.isfinite(v):
                raise ClipError(f"{source}: row {r}, column {header[i]!r}: not finite ({row[i]!r})")
            series[shape].append(min(max(v, 0.0), 1.0))
    if not times:
        raise ClipError(f"{source}: no data rows")
    t0 = times[0]
    rel = [t - t0 for t in times]
    doc = ClipDoc(name)
    for shape in ARKIT_BLENDSHAPES:
        channel = "arkit." + shape
        values = series[shape]
        if (wanted is not None and channel not in wanted) or max(values) <= tolerance:
            continue
        keep = reduce_keys(rel, values, tolerance)
        doc.tracks[channel] = Track("linear", [Key(rel[i], values[i]) for i in keep])
    if not doc.tracks:
        raise ClipError(f"{source}: every blendshape stays at zero (or none is served by this head)")
    doc.version += 1
    return doc
