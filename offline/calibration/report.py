"""Calibration outputs: ``report.json`` (per-link hold-out errors and more) and a PNG plot.

``report.json`` always has ``{"links": {name: {"rms_mm", "max_mm", "rms_deg"}}, "holdout_rms_mm": ...}``
(hold-out errors against the tracker), plus the training residuals, the noise floor measured from the
repeated neutral poses, detected actuators per link, discovered limits and zero offsets.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path, write_text


def write_report(path: Path, report: Mapping[str, Any]) -> Path:
    """Write the report JSON atomically."""
    write_text(path, json.dumps(report, indent=1, allow_nan=False, default=_jsonable) + "\n")
    return path


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def write_plot(path: Path, report: Mapping[str, Any], holdout_errors_mm: Mapping[str, np.ndarray]) -> Path:
    """Bar chart of per-link hold-out RMS/max (mm) against the noise floor, and the error distribution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    links = list(report["links"])
    rms = [report["links"][n]["rms_mm"] for n in links]
    mx = [report["links"][n]["max_mm"] for n in links]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    x = np.arange(len(links))
    ax1.bar(x - 0.2, rms, 0.4, label="hold-out RMS")
    ax1.bar(x + 0.2, mx, 0.4, label="hold-out max")
    floor = report.get("noise_floor_mm")
    if floor:
        ax1.axhline(floor, color="k", ls="--", lw=1, label="pose noise floor (neutral repeats)")
    ax1.set_xticks(x, links, rotation=45, ha="right")
    ax1.set_ylabel("position error (mm)")
    ax1.set_title(f"{report.get('head', '')}: hold-out RMS {report['holdout_rms_mm']:.3f} mm")
    ax1.legend(fontsize=8)
    allerr = np.concatenate([np.asarray(v) for v in holdout_errors_mm.values()]) if holdout_errors_mm else np.zeros(0)
    if allerr.size:
        ax2.hist(allerr, bins=30, color="tab:blue", alpha=0.8)
    ax2.set_xlabel("hold-out position error (mm)")
    ax2.set_ylabel("link poses")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path
