"""A daemon recording (``.lrec``, or the older ``.npz``) as a clip map, so a take can come back into Blender as an
action: the commanded (or measured) curve of every actuator, linear, thinned to at most one key per ``step``
seconds. Reads the file format documented in docs/operations.md, without the runtime package.
"""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import SpecError

LREC_FORMAT = "likeness.recording"


def read_recording(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(t, commanded, measured, names) of a recording; :class:`SpecError` naming the file when it is not one."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SpecError(str(path), "file", f"cannot read recording: {exc.strerror or exc}") from exc
    if data[:1] == b"{":
        end = data.find(b"\n")
        try:
            header = json.loads(data[:end]) if end > 0 else None
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SpecError(str(path), "header", f"recording header is not JSON ({exc})") from exc
        if not isinstance(header, dict) or header.get("format") != LREC_FORMAT or header.get("dtype") != "<f8":
            raise SpecError(str(path), "header", f"not a recording (format is not {LREC_FORMAT!r} with dtype '<f8')")
        names = [str(n) for n in header.get("names", [])]
        cols = 1 + 2 * len(names)
        if header.get("columns") != cols:
            raise SpecError(str(path), "header", "names and columns do not agree")
        body = data[end + 1:]
        n = len(body) // (8 * cols)
        rows = np.frombuffer(body, dtype="<f8", count=n * cols).reshape(n, cols)
        k = len(names)
        return rows[:, 0].copy(), rows[:, 1:1 + k].copy(), rows[:, 1 + k:].copy(), names
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {key: z[key] for key in ("t", "commanded", "measured", "names")}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise SpecError(str(path), "file", f"not a recording (.lrec, or .npz with t, commanded, measured, "
                        f"names): {exc}") from exc
    return (np.asarray(arrays["t"], float), np.asarray(arrays["commanded"], float),
            np.asarray(arrays["measured"], float), [str(n) for n in arrays["names"]])


def recording_clip(path: str | Path, which: str = "commanded", step: float = 1 / 120,
                   name: str | None = None) -> dict[str, Any]:
    """The clip map of a recording's ``commanded`` or ``measured`` curves (linear keys, times from its first row)."""
    if which not in ("commanded", "measured"):
        raise SpecError(str(path), "curves", f"must be 'commanded' or 'measured' (got {which!r})")
    t, commanded, measured, names = read_recording(path)
    values = commanded if which == "commanded" else measured
    if not len(t):
        raise SpecError(str(path), "records", "the recording holds no frames")
    channels: dict[str, Any] = {}
    for j, ch in enumerate(names):
        ok = np.isfinite(values[:, j]) & np.isfinite(t)
        tj, vj = t[ok] - t[0], values[ok, j]
        if not len(tj):
            continue
        slot = np.floor(tj / step) if step > 0 else np.arange(len(tj))
        keep = np.r_[True, np.diff(slot) > 0] & np.r_[True, np.diff(tj) > 0]
        keep[-1] = keep[-1] or (len(tj) > 1 and tj[-1] > tj[keep][-1])
        channels[ch] = {"interp": "linear", "keys": np.column_stack([tj[keep], vj[keep]]).tolist()}
    if not channels:
        raise SpecError(str(path), which, "no finite values in the recording")
    stem = name or Path(path).stem
    return {"name": stem[:128], "channels": channels, "meta": {"source": str(path), "curves": which,
                                                              "step_s": step if math.isfinite(step) else None}}
