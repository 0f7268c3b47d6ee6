"""Recordings of commanded and measured trajectories: the streamed ``.lrec`` file, the older ``.npz``, and plots.

Two file formats hold the same columns: ``t`` (s from the first row), ``commanded`` and ``measured`` (samples ×
actuators, in each actuator's configured unit), ``names``, ``units``, ``meta``.

* ``.lrec`` (written while recording by :class:`RecordingWriter`, append-only, crash-safe): one JSON header line
  (UTF-8, ending in a newline, padded with spaces so its length is a multiple of 8 bytes) with ``format``
  (:data:`LREC_FORMAT`), ``version``, ``names``, ``units``, ``columns`` (``1 + 2 × actuators``), ``dtype``
  (``"<f8"``) and ``meta``; then fixed-size records of ``columns`` little-endian float64 each:
  ``[t, commanded..., measured...]``. A file cut at any byte (``kill -9``, power loss) reads up to its last complete
  record: the reader ignores a trailing partial record.
* ``.npz`` (written at once by :meth:`Recorder.save`): arrays ``t``, ``commanded``, ``measured``, ``names``,
  ``units`` and ``meta`` (JSON text).

The control thread appends one row per cycle into preallocated arrays (no allocation per cycle); :meth:`Recorder.save`
writes an ``.npz`` atomically.
"""

from __future__ import annotations

import json
import os
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path


class Recorder:
    """Fixed-capacity recording of commanded/measured positions; rows beyond capacity are counted, not stored."""

    def __init__(self, names: Sequence[str], units: Sequence[str], scale: Sequence[float], capacity: int,
                 meta: dict[str, Any] | None = None) -> None:
        self.names = list(names)
        self.units = list(units)
        self._inv = 1.0 / np.asarray(scale, dtype=float)  # SI → configured unit
        self.capacity = capacity
        n = len(names)
        self.t = np.empty(capacity)
        self.cmd = np.empty((capacity, n))  # pages are touched only as rows are written
        self.meas = np.empty((capacity, n))
        self.count = 0
        self.dropped = 0
        self.t0: float | None = None
        self.meta = dict(meta or {})

    def add(self, now: float, commanded_si: np.ndarray, measured_si: np.ndarray) -> None:
        if self.t0 is None:
            self.t0 = now
        i = self.count
        if i >= self.capacity:
            self.dropped += 1
            return
        self.t[i] = now - self.t0
        self.cmd[i] = commanded_si * self._inv
        self.meas[i] = measured_si * self._inv
        self.count = i + 1

    def save(self, path: str | Path) -> Path:
        """Write the recording atomically; returns the path."""
        path = Path(path)
        n = self.count
        meta = dict(self.meta, dropped=self.dropped, samples=n)
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(
                tmp, t=self.t[:n], commanded=self.cmd[:n], measured=self.meas[:n],
                names=np.array(self.names), units=np.array(self.units), meta=np.array(json.dumps(meta)),
            )
        return path


#: ``format`` value of an ``.lrec`` header.
LREC_FORMAT = "likeness.recording"
LREC_VERSION = 1
LREC_SUFFIX = ".lrec"
MAX_HEADER = 1 << 20  # bytes; a longer first line is not a recording header


class RecordingWriter:
    """Appends rows ``[t, commanded..., measured...]`` (configured units) to an ``.lrec`` file as they arrive.

    Each :meth:`append` hands its bytes to the operating system at once (so a killed process loses nothing it
    appended), and the file is fsynced when the last sync is ``sync_s`` old or more (so a power loss loses at most
    about that much) and on :meth:`close`. Time is stored relative to ``t0`` (default: the first row's ``t``).
    """

    def __init__(self, path: str | Path, names: Sequence[str], units: Sequence[str],
                 meta: dict[str, Any] | None = None, *, t0: float | None = None, sync_s: float = 1.0) -> None:
        self.path = Path(path)
        self.names = [str(n) for n in names]
        self.units = [str(u) for u in units]
        if len(self.units) != len(self.names):
            raise ValueError(f"{self.path}: {len(self.names)} names but {len(self.units)} units")
        self.columns = 1 + 2 * len(self.names)
        self.t0 = t0
        self.sync_s = float(sync_s)
        self.rows = 0
        header = {"format": LREC_FORMAT, "version": LREC_VERSION, "names": self.names, "units": self.units,
                  "columns": self.columns, "dtype": "<f8", "meta": dict(meta or {})}
        line = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
        line += b" " * (-(len(line) + 1) % 8) + b"\n"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o666)
        self._write(line)
        self._sync()

    def append(self, rows: np.ndarray) -> None:
        """Append rows (one row or a 2-D block of shape (n, columns)); ValueError on a wrong width."""
        if self._fd is None:
            raise ValueError(f"{self.path}: recording is closed")
        block = np.asarray(rows, dtype=float)
        if block.ndim == 1:
            block = block[None, :]
        if block.ndim != 2 or block.shape[1] != self.columns:
            raise ValueError(f"{self.path}: rows must have {self.columns} columns (got shape {block.shape})")
        if not len(block):
            return
        if self.t0 is None:
            self.t0 = float(block[0, 0])
        block = block.astype("<f8", copy=True)
        block[:, 0] -= self.t0
        self._write(block.tobytes())
        self.rows += len(block)
        if time.monotonic() - self._synced >= self.sync_s:
            self._sync()

    def flush(self) -> None:
        """Force what was appended to disk now."""
        if self._fd is not None:
            self._sync()

    def close(self) -> None:
        """Sync and close (idempotent)."""
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]

    def _sync(self) -> None:
        os.fsync(self._fd)
        self._synced = time.monotonic()


def read_lrec_header(path: str | Path) -> tuple[dict[str, Any], int]:
    """The header of an ``.lrec`` file and its length in bytes; ValueError naming the file and what is wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            line = fh.readline(MAX_HEADER)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    if not line.endswith(b"\n"):
        raise ValueError(f"{path}: incomplete recording header (no end of line within the first {len(line)} bytes)")
    try:
        header = json.loads(line)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: recording header is not JSON ({exc})") from exc
    if not isinstance(header, dict) or header.get("format") != LREC_FORMAT:
        raise ValueError(f"{path}: not a recording file (header format is not {LREC_FORMAT!r})")
    if header.get("version") != LREC_VERSION or header.get("dtype") != "<f8":
        raise ValueError(f"{path}: unsupported recording version {header.get('version')!r} "
                         f"or dtype {header.get('dtype')!r} (expected {LREC_VERSION}, '<f8')")
    names, units = header.get("names"), header.get("units")
    if (not isinstance(names, list) or not isinstance(units, list) or len(names) != len(units)
            or header.get("columns") != 1 + 2 * len(names)):
        raise ValueError(f"{path}: recording header: names, units and columns do not agree")
    return header, len(line)


def recording_summary(path: str | Path) -> tuple[int, float]:
    """(complete frames, time span in s) of a recording, reading only the header and the first and last frames of an
    ``.lrec`` file; ValueError naming the file when it is not a recording."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            first = fh.read(1)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    if first != b"{":
        t = load_recording(path)["t"]
        return len(t), float(t[-1] - t[0]) if len(t) else 0.0
    header, start = read_lrec_header(path)
    size = 8 * header["columns"]
    with open(path, "rb") as fh:
        n = (os.fstat(fh.fileno()).st_size - start) // size
        if n == 0:
            return 0, 0.0
        fh.seek(start)
        t0 = np.frombuffer(fh.read(8), "<f8")[0]
        fh.seek(start + (n - 1) * size)
        t1 = np.frombuffer(fh.read(8), "<f8")[0]
    return int(n), float(t1 - t0)


def _load_lrec(path: Path) -> dict[str, Any]:
    header, start = read_lrec_header(path)
    cols = header["columns"]
    with open(path, "rb") as fh:
        fh.seek(start)
        data = fh.read()
    n = len(data) // (8 * cols)
    block = np.frombuffer(data, dtype="<f8", count=n * cols).reshape(n, cols).astype(float)
    k = len(header["names"])
    meta = dict(header.get("meta") or {}, samples=n, partial_bytes=len(data) - n * 8 * cols)
    return {"t": block[:, 0], "commanded": block[:, 1:1 + k], "measured": block[:, 1 + k:],
            "names": [str(x) for x in header["names"]], "units": [str(x) for x in header["units"]], "meta": meta}


def load_recording(path: str | Path) -> dict[str, Any]:
    """Read a recording file (``.lrec`` or ``.npz``); ValueError naming the file and what is wrong when malformed."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            first = fh.read(1)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    if first == b"{":
        return _load_lrec(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, AttributeError) as exc:
        raise ValueError(f"{path}: not a recording file ({exc})") from exc
    for key in ("t", "commanded", "measured", "names", "units"):
        if key not in out:
            raise ValueError(f"{path}: recording lacks array {key!r}")
    out["names"] = [str(x) for x in out["names"]]
    out["units"] = [str(x) for x in out["units"]]
    out["meta"] = json.loads(str(out["meta"])) if "meta" in out else {}
    return out


def tracking_errors(rec: dict[str, Any], settle_s: float = 0.0) -> dict[str, dict[str, float]]:
    """Per actuator RMS and max |commanded − measured| (configured units), skipping the first ``settle_s``."""
    keep = rec["t"] >= settle_s
    out = {}
    for j, name in enumerate(rec["names"]):
        err = rec["commanded"][keep, j] - rec["measured"][keep, j]
        err = err[np.isfinite(err)]
        if err.size:
            out[name] = {"rms": float(np.sqrt(np.mean(err**2))), "max": float(np.max(np.abs(err))),
                         "unit": rec["units"][j]}
    return out


def plot_recording(rec: dict[str, Any], out: str | Path, title: str = "") -> Path:
    """Commanded (dashed) versus measured (solid) per actuator, one panel each, written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    names = rec["names"]
    n = len(names)
    cols = 3 if n > 4 else 1
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 1.9 * rows), sharex=True, squeeze=False)
    t = rec["t"]
    for j, name in enumerate(names):
        ax = axes[j // cols][j % cols]
        ax.plot(t, rec["commanded"][:, j], "--", lw=1.0, label="commanded")
        ax.plot(t, rec["measured"][:, j], "-", lw=1.0, alpha=0.8, label="measured")
        ax.set_title(f"{name} [{rec['units'][j]}]", fontsize=9)
        ax.tick_params(labelsize=7)
        if j == 0:
            ax.legend(fontsize=7, loc="upper right")
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]", fontsize=8)
    fig.suptitle(title or "commanded vs measured", fontsize=11)
    fig.tight_layout()
    try:
        with atomic_path(out, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=90, format="png")
    finally:
        plt.close(fig)
    return out


#: Keys a replay clip holds at most (all channels together): keeps its ``load_clip`` request under 1 MiB.
REPLAY_MAX_KEYS = 40_000


def replay_clip(rec: dict[str, Any], name: str, max_keys: int = REPLAY_MAX_KEYS) -> dict[str, Any]:
    """The protocol clip map of a recording's commanded curves (linear), decimated to at most ``max_keys`` keys."""
    import math

    t = np.asarray(rec["t"], dtype=float)
    cmd = np.asarray(rec["commanded"], dtype=float)
    channels: dict[str, Any] = {}
    per_channel = max(2, max_keys // max(1, len(rec["names"])))
    for j, ch in enumerate(rec["names"]):
        ok = np.isfinite(cmd[:, j]) & np.isfinite(t)
        tj, vj = t[ok] - (t[0] if len(t) else 0.0), cmd[ok, j]
        if not len(tj):
            continue
        stride = max(1, math.ceil(len(tj) / per_channel))
        idx = np.unique(np.r_[np.arange(0, len(tj), stride), len(tj) - 1])
        keep = idx[np.r_[True, np.diff(tj[idx]) > 0]]  # strictly increasing times
        channels[ch] = {"interp": "linear", "keys": np.column_stack([tj[keep], vj[keep]]).tolist()}
    return {"name": name[:128], "channels": channels}
