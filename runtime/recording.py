"""Recording of commanded and measured trajectories (``.npz``), and their plot as a PNG.

The control thread appends one row per cycle into preallocated arrays (no allocation per cycle); :meth:`save`
writes atomically. File contents: ``t`` (s from start), ``commanded`` and ``measured`` (samples × actuators, in each
actuator's configured unit), ``names``, ``units``, ``meta`` (JSON text).
"""

from __future__ import annotations

import json
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


def load_recording(path: str | Path) -> dict[str, Any]:
    """Read a recording file; ValueError naming the file and the missing array when malformed."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
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
