"""Animation clips: per-channel keyframe curves (step, linear, cubic Bezier) and their JSON and CSV files.

The clip format every package shares: the daemon compiles clips for its loop (``runtime.compiled``), offline tools
sample performances, and the studio edits and draws them. Evaluation here is the per-key reference
(:meth:`Curve.value`); the loop's array evaluation lives in the runtime.

A clip is ``{"name": str, "channels": {channel: {"keys": [[t, value], ...], "interp": "step" | "linear"}}}``;
Bezier channels (``"interp": "bezier"``) give each key its tangent handles as offsets from the key,
``[t, value, in_dt, in_dv, out_dt, out_dv]`` (``in_dt <= 0 <= out_dt``, as animation tools export them). Values are in
the channel's configured unit. Every validation error is a :class:`ClipError` naming the clip, channel, key and value.
"""

from __future__ import annotations

import bisect
import csv
import io
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models.errors import SpecError
from models.jsonfile import parse_json, read_text

INTERPS = ("step", "linear", "bezier")
MAX_CHANNELS = 256
MAX_KEYS = 200_000  # per clip, all channels together
MAX_NAME = 128


class ClipError(ValueError):
    """A clip (or streamed frame) is malformed; the message names where and what."""


@dataclass(frozen=True)
class Curve:
    """One channel's keyframes; :meth:`value` evaluates it (held constant before the first and after the last key)."""

    interp: str
    times: tuple[float, ...]
    values: tuple[float, ...]
    # Bezier only: per segment the cubic coefficients of time and value in the segment parameter s ∈ [0, 1].
    _seg: tuple[tuple[float, ...], ...] = ()

    @property
    def start(self) -> float:
        return self.times[0]

    @property
    def end(self) -> float:
        return self.times[-1]

    def value(self, t: float) -> float:
        """Curve value at time ``t``."""
        times = self.times
        if t <= times[0]:
            return self.values[0]
        if t >= times[-1]:
            return self.values[-1]
        i = bisect.bisect_right(times, t) - 1
        if self.interp == "step":
            return self.values[i]
        t0, t1 = times[i], times[i + 1]
        if self.interp == "linear":
            u = (t - t0) / (t1 - t0)
            return self.values[i] + u * (self.values[i + 1] - self.values[i])
        return _bezier_eval(self._seg[i], t, (t - t0) / (t1 - t0))


def _bezier_eval(seg: tuple[float, ...], t: float, guess: float) -> float:
    """Solve x(s) = t for s (monotonic x: Newton with bisection safeguard), then return y(s)."""
    xa, xb, xc, xd, ya, yb, yc, yd = seg
    lo, hi = 0.0, 1.0
    s = guess
    for _ in range(24):
        x = ((xa * s + xb) * s + xc) * s + xd - t
        if abs(x) < 1e-10:
            break
        if x > 0:
            hi = s
        else:
            lo = s
        dx = (3 * xa * s + 2 * xb) * s + xc
        s_new = s - x / dx if dx > 1e-12 else 0.5 * (lo + hi)
        s = s_new if lo < s_new < hi else 0.5 * (lo + hi)
    return ((ya * s + yb) * s + yc) * s + yd


def _cubic(p0: float, p1: float, p2: float, p3: float) -> tuple[float, float, float, float]:
    """Power-basis coefficients (a, b, c, d) of a cubic Bezier with control values p0..p3."""
    return (-p0 + 3 * p1 - 3 * p2 + p3, 3 * p0 - 6 * p1 + 3 * p2, -3 * p0 + 3 * p1, p0)


def make_curve(interp: str, keys: Sequence[Sequence[float]], where: str = "curve") -> Curve:
    """Validate keys (finite numbers, strictly increasing times) and build a curve."""
    if interp not in INTERPS:
        raise ClipError(f"{where}.interp: must be one of {', '.join(INTERPS)} (got {interp!r})")
    if not isinstance(keys, (list, tuple)) or not keys:
        raise ClipError(f"{where}.keys: must be a non-empty list of keys (got {_short(keys)})")
    width = 6 if interp == "bezier" else 2
    rows: list[tuple[float, ...]] = []
    for j, key in enumerate(keys):
        if not isinstance(key, (list, tuple)) or len(key) != width:
            raise ClipError(f"{where}.keys[{j}]: must be a list of {width} numbers for {interp} (got {_short(key)})")
        row = []
        for k, x in enumerate(key):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise ClipError(f"{where}.keys[{j}][{k}]: must be a finite number (got {_short(x)})")
            row.append(float(x))
        if rows and row[0] <= rows[-1][0]:
            raise ClipError(f"{where}.keys[{j}]: times must increase strictly ({row[0]!r} after {rows[-1][0]!r})")
        if interp == "bezier" and (row[2] > 0 or row[4] < 0):
            raise ClipError(f"{where}.keys[{j}]: need in_dt <= 0 <= out_dt (got in_dt={row[2]!r}, out_dt={row[4]!r})")
        rows.append(tuple(row))
    times = tuple(r[0] for r in rows)
    values = tuple(r[1] for r in rows)
    seg: list[tuple[float, ...]] = []
    if interp == "bezier":
        for a, b in itertools.pairwise(rows):
            span = b[0] - a[0]
            # Handles beyond the segment would make time non-monotonic: scale them back (value scaled alike).
            fo = min(1.0, span / a[4]) if a[4] > 0 else 1.0
            fi = min(1.0, span / -b[2]) if b[2] < 0 else 1.0
            p1 = (a[0] + a[4] * fo, a[1] + a[5] * fo)
            p2 = (b[0] + b[2] * fi, b[1] + b[3] * fi)
            seg.append(_cubic(a[0], p1[0], p2[0], b[0]) + _cubic(a[1], p1[1], p2[1], b[1]))
    return Curve(interp, times, values, tuple(seg))


@dataclass(frozen=True)
class Clip:
    """A named set of channel curves; ``duration`` is the last key time over all channels (starts at 0)."""

    name: str
    channels: Mapping[str, Curve]

    @property
    def duration(self) -> float:
        return max(c.end for c in self.channels.values())

    def sample(self, t: float) -> dict[str, float]:
        """Every channel's value at clip time ``t``."""
        return {name: c.value(t) for name, c in self.channels.items()}

    def key_count(self) -> int:
        return sum(len(c.times) for c in self.channels.values())


def clip_from_dict(data: Any, where: str = "clip") -> Clip:
    """Validate a clip map (the protocol's and the JSON file's format)."""
    if not isinstance(data, Mapping):
        raise ClipError(f"{where}: must be a map with 'name' and 'channels' (got {_short(data)})")
    extra = set(data) - {"name", "channels", "meta"}
    if extra:
        raise ClipError(f"{where}: unknown key(s) {sorted(map(str, extra))}; allowed: name, channels, meta")
    name = data.get("name")
    if not isinstance(name, str) or not name or len(name) > MAX_NAME:
        raise ClipError(f"{where}.name: must be a string of 1..{MAX_NAME} characters (got {_short(name)})")
    where = f"clip {name!r}"
    channels = data.get("channels")
    if not isinstance(channels, Mapping) or not channels:
        raise ClipError(f"{where}.channels: must be a non-empty map of channel curves (got {_short(channels)})")
    if len(channels) > MAX_CHANNELS:
        raise ClipError(f"{where}.channels: at most {MAX_CHANNELS} channels (got {len(channels)})")
    curves: dict[str, Curve] = {}
    total = 0
    for ch, spec in channels.items():
        if not isinstance(ch, str) or not ch or len(ch) > MAX_NAME:
            raise ClipError(f"{where}.channels: channel names must be strings of 1..{MAX_NAME} chars ({_short(ch)})")
        cw = f"{where}.channels.{ch}"
        if not isinstance(spec, Mapping):
            raise ClipError(f"{cw}: must be a map with 'keys' and 'interp' (got {_short(spec)})")
        bad = set(spec) - {"keys", "interp"}
        if bad:
            raise ClipError(f"{cw}: unknown key(s) {sorted(map(str, bad))}; allowed: keys, interp")
        keys = spec.get("keys")
        if isinstance(keys, (list, tuple)):
            total += len(keys)
            if total > MAX_KEYS:
                raise ClipError(f"{where}: more than {MAX_KEYS} keys")
        curves[ch] = make_curve(spec.get("interp", "linear"), keys, cw)
    return Clip(name, curves)


def clip_to_dict(clip: Clip) -> dict[str, Any]:
    """The JSON/protocol map of a clip whose curves are step or linear (Bezier handles are not kept)."""
    out: dict[str, Any] = {}
    for ch, c in clip.channels.items():
        if c.interp == "bezier":
            raise ClipError(f"clip {clip.name!r}.channels.{ch}: Bezier curves are not re-exported")
        out[ch] = {"interp": c.interp, "keys": [[t, v] for t, v in zip(c.times, c.values, strict=True)]}
    return {"name": clip.name, "channels": out}


def clip_from_csv(text: str, name: str, interp: str = "linear", source: str = "<csv>") -> Clip:
    """A clip from CSV: a ``time`` (or ``t``) column, then one column per channel; empty cells are no key."""
    if interp not in ("step", "linear"):
        raise ClipError(f"{source}: CSV interpolation must be step or linear (got {interp!r})")
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except StopIteration:
        raise ClipError(f"{source}: empty CSV file") from None
    header = [h.strip() for h in header]
    if not header or header[0].lower() not in ("time", "t"):
        raise ClipError(f"{source}: row 1 column 1 must be 'time' (got {header[0] if header else ''!r})")
    if len(header) < 2:
        raise ClipError(f"{source}: row 1 needs at least one channel column after 'time'")
    channels = header[1:]
    if len(set(channels)) != len(channels) or any(not c for c in channels):
        raise ClipError(f"{source}: row 1: channel names must be unique and non-empty (got {channels})")
    keys: dict[str, list[list[float]]] = {c: [] for c in channels}
    for rowno, row in enumerate(reader, start=2):
        if not row or all(not x.strip() for x in row):
            continue
        if len(row) != len(header):
            raise ClipError(f"{source}: row {rowno}: expected {len(header)} cells, got {len(row)}")
        t = _csv_number(row[0], source, rowno, "time")
        for c, cell in zip(channels, row[1:], strict=True):
            if cell.strip():
                keys[c].append([t, _csv_number(cell, source, rowno, c)])
    data = {"name": name, "channels": {c: {"interp": interp, "keys": k} for c, k in keys.items() if k}}
    if not data["channels"]:
        raise ClipError(f"{source}: no data rows")
    return clip_from_dict(data, where=source)


def _csv_number(cell: str, source: str, row: int, column: str) -> float:
    try:
        x = float(cell)
    except ValueError:
        raise ClipError(f"{source}: row {row}, column {column!r}: not a number ({cell!r})") from None
    if not math.isfinite(x):
        raise ClipError(f"{source}: row {row}, column {column!r}: not finite ({cell!r})")
    return x


def load_clip_file(path: str | Path, interp: str = "linear") -> Clip:
    """Load a clip from ``.json`` (the clip map) or ``.csv`` (named after the file)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return clip_from_csv(_clip_text(path), path.stem, interp, str(path))
    return clip_from_dict(_clip_json(path), where=str(path))


def _clip_text(path: Path) -> str:
    try:
        return read_text(path, "clip")
    except SpecError as exc:  # unreadable or not UTF-8: one line naming the file and byte
        raise ClipError(str(exc)) from None


def _clip_json(path: Path) -> Any:
    try:
        return parse_json(_clip_text(path), str(path), "clip")
    except SpecError as exc:  # syntax error or nesting too deep: one line naming the file and position
        raise ClipError(str(exc)) from None


def clip_file_as_dict(path: str | Path, interp: str = "linear") -> dict[str, Any]:
    """The protocol map for a clip file: JSON files as written (keeps Bezier tangents), CSV converted."""
    path = Path(path)
    clip = load_clip_file(path, interp)  # validates either way
    if path.suffix.lower() == ".csv":
        return clip_to_dict(clip)
    return _clip_json(path)


def _short(x: Any, limit: int = 60) -> str:
    text = repr(x)
    return text if len(text) <= limit else text[: limit - 3] + "..."
