"""Marker capture data shared by real capture systems, the simulated tracker and calibration.

A capture system reports, per frame, one marker frame (rigid body) per tracked link: a timestamp, the link
name, a position in metres and an orientation quaternion ``(w, x, y, z)``. Formats (``docs/tracker.md``):

- CSV export, one row per marker per frame: ``time,link,x,y,z,qw,qx,qy,qz`` (seconds, metres, unit quaternion);
- ZeroMQ stream (version 1): two-part messages ``[b"tracker", msgpack(body)]`` with
  ``body = {"v": 1, "time": t, "frame": i, "markers": {link: [x, y, z, qw, qx, qy, qz]}}``; this module builds
  and validates ``body`` (:func:`frame_body`, :func:`samples_from_body`), the transport packs it.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from models.atomic import write_text
from models.errors import SpecError

CSV_COLUMNS = ("time", "link", "x", "y", "z", "qw", "qx", "qy", "qz")
TOPIC = b"tracker"
STREAM_VERSION = 1


@dataclass(frozen=True)
class MarkerSample:
    """One tracked marker frame: capture time (s), link name, position (m), quaternion (w, x, y, z)."""

    time: float
    link: str
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]


# ---------------------------------------------------------------------------- CSV export / replay
def samples_to_csv(samples: Iterable[MarkerSample]) -> str:
    """CSV text with a header row and one row per marker sample."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for s in samples:
        w.writerow([f"{s.time:.6f}", s.link, *(f"{v:.7f}" for v in s.position), *(f"{v:.8f}" for v in s.quaternion)])
    return buf.getvalue()


def write_csv(path: str | Path, samples: Iterable[MarkerSample]) -> Path:
    """Write samples as a capture export CSV, atomically."""
    path = Path(path)
    write_text(path, samples_to_csv(samples))
    return path


class CsvAppender:
    """Append samples to a capture CSV as they arrive (the header is written once)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._fh = self.path.open("a", encoding="utf-8", newline="")
        if new:
            self._fh.write(",".join(CSV_COLUMNS) + "\n")

    def write(self, samples: Iterable[MarkerSample]) -> None:
        text = samples_to_csv(samples)
        self._fh.write(text.split("\n", 1)[1])
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def read_csv(path: str | Path) -> list[MarkerSample]:
    """Read a capture export; errors name the file, row and column."""
    path = Path(path)
    src = str(path)
    try:
        fh = path.open(encoding="utf-8", newline="")
    except OSError as exc:
        raise SpecError(src, "file", f"cannot read capture CSV: {exc.strerror or exc}") from exc
    out: list[MarkerSample] = []
    with fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or [h.strip().lower() for h in header] != list(CSV_COLUMNS):
            raise SpecError(src, "header", f"expected columns {','.join(CSV_COLUMNS)}", header)
        for i, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(CSV_COLUMNS):
                raise SpecError(src, f"row {i}", f"expected {len(CSV_COLUMNS)} columns, got {len(row)}", row)
            try:
                vals = [float(row[0]), *(float(v) for v in row[2:])]
            except ValueError as exc:
                raise SpecError(src, f"row {i}", f"not a number: {exc}", row) from exc
            if not all(math.isfinite(v) for v in vals):
                raise SpecError(src, f"row {i}", "values must be finite", row)
            q = vals[4:]
            if math.sqrt(sum(v * v for v in q)) < 1e-6:
                raise SpecError(src, f"row {i} (qw..qz)", "quaternion has zero length", q)
            if not row[1]:
                raise SpecError(src, f"row {i} (link)", "empty link name")
            out.append(MarkerSample(vals[0], row[1], tuple(vals[1:4]), tuple(q)))
    return out


class CaptureLog:
    """Recorded samples indexed by time, for replaying the windows a calibration journal names."""

    def __init__(self, samples: Sequence[MarkerSample]) -> None:
        self.samples = sorted(samples, key=lambda s: s.time)
        self._times = np.array([s.time for s in self.samples])

    def between(self, t0: float, t1: float) -> list[MarkerSample]:
        """Samples with ``t0 <= time <= t1`` (1 µs tolerance for rounding in exports)."""
        i = int(np.searchsorted(self._times, t0 - 1e-6, side="left"))
        j = int(np.searchsorted(self._times, t1 + 1e-6, side="right"))
        return self.samples[i:j]


# ---------------------------------------------------------------------------- stream frames
def frame_body(frame_index: int, samples: Sequence[MarkerSample]) -> dict[str, Any]:
    """The map sent for one capture frame (all samples share the frame's time)."""
    t = samples[0].time if samples else 0.0
    return {
        "v": STREAM_VERSION,
        "time": t,
        "frame": frame_index,
        "markers": {s.link: [*s.position, *s.quaternion] for s in samples},
    }


def samples_from_body(body: Any) -> list[MarkerSample]:
    """Marker samples of one received frame; ``ValueError`` naming what is wrong on a bad frame."""
    if not isinstance(body, Mapping) or body.get("v") != STREAM_VERSION:
        version = body.get("v") if isinstance(body, Mapping) else None
        raise ValueError(f"unsupported tracker frame (v={version!r}, expected {STREAM_VERSION})")
    try:
        t = float(body["time"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError("tracker frame needs a numeric 'time'") from exc
    markers = body.get("markers", {})
    if not isinstance(markers, Mapping):
        raise ValueError("tracker frame 'markers' must be a map")
    out = []
    for link, vals in markers.items():
        if not isinstance(vals, (list, tuple)) or len(vals) != 7:
            raise ValueError(f"marker {link!r}: expected [x, y, z, qw, qx, qy, qz]")
        v = [float(x) for x in vals]
        if not all(math.isfinite(x) for x in v) or math.sqrt(sum(x * x for x in v[3:])) < 1e-6:
            raise ValueError(f"marker {link!r}: values must be finite with a non-zero quaternion")
        out.append(MarkerSample(t, str(link), (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6])))
    return out


def pack_frame(frame_index: int, samples: Sequence[MarkerSample]) -> list[bytes]:
    """The two-part ZeroMQ message of one capture frame."""
    return [TOPIC, msgpack.packb(frame_body(frame_index, samples), use_bin_type=True)]


def unpack_frame(parts: Sequence[bytes]) -> list[MarkerSample]:
    """Marker samples of one received message; ``ValueError`` naming what is wrong on a bad message."""
    if len(parts) != 2 or parts[0] != TOPIC:
        raise ValueError("expected a two-part message [b'tracker', msgpack frame]")
    try:
        body = msgpack.unpackb(parts[1], raw=False)
    except Exception as exc:
        raise ValueError(f"undecodable tracker frame: {exc}") from exc
    return samples_from_body(body)
