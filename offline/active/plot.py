"""The benchmark figure (the paper's Fig. 5): test error against labelled samples, mean and 95 % band over seeds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path

STYLE = {"random": ("black", "-"), "greedy": ("tab:gray", ":"), "space_filling": ("tab:green", "--"),
         "committee": ("tab:purple", "-."), "lcmd": ("tab:blue", "-"), "maxdist": ("tab:cyan", "--"),
         "genlal": ("tab:red", "-")}


def plot_curves(runs: dict[str, list[dict[str, Any]]], path: str | Path, title: str = "") -> Path:
    """PNG with two panels (mean Euclidean error, L1) against samples: mean over seeds, band its 95 % interval."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(7.5, 8.0), sharex=True)
    for name, rs in runs.items():
        if not rs:
            continue
        n = np.asarray(rs[0]["n_labelled"], float)
        color, ls = STYLE.get(name, ("tab:orange", "-"))
        for ax, key in zip(axes, ("mean_euclidean_um", "l1_um"), strict=True):
            curves = np.array([r[key] for r in rs if len(r[key]) == len(n)])
            ax.plot(n, curves.mean(axis=0), color=color, ls=ls, lw=2 if name == "genlal" else 1.4,
                    label=f"{name} ({len(curves)} seeds)")
            if len(curves) > 1:
                from scipy import stats

                h = stats.t.ppf(0.975, len(curves) - 1) * curves.std(axis=0, ddof=1) / np.sqrt(len(curves))
                ax.fill_between(n, curves.mean(axis=0) - h, curves.mean(axis=0) + h, color=color, alpha=0.15)
    axes[0].set_ylabel("test mean Euclidean vertex error (µm)")
    axes[1].set_ylabel("test L1, mean |coordinate error| (µm)")
    axes[1].set_xlabel("labelled poses (simulated)")
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        axes[0].set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
