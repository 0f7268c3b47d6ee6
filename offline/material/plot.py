"""Plot measured versus simulated force–strain curves of a material fit (PNG, matplotlib's Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.atomic import atomic_path
from offline.material.fit import FitResult, closed_form_forces
from offline.material.specimen import SpecimenPlan


def plot_fit(result: FitResult, plan: SpecimenPlan, path: str | Path, title: str = "") -> Path:
    """Write a PNG with, per specimen, measured samples, each optimiser's curve and the residuals; atomic write."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    groups = plan.for_strains(result.strain)
    fig, axes = plt.subplots(2, len(groups), figsize=(6.0 * len(groups), 6.5), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1]}, sharex="col")
    styles = {"anneal": ("tab:red", "-"), "lsq": ("tab:blue", "--")}
    for col, (spec, mask) in enumerate(groups):
        ax, axr = axes[0, col], axes[1, col]
        eps = result.strain[mask]
        ax.plot(eps * 100, result.measured[mask], "ko", ms=4, mfc="none", label="measured")
        for run in result.runs:
            color, ls = styles.get(run.method, ("tab:green", "-"))
            label = f"{run.method}: E = {run.params.E / 1e3:.1f} kPa, ν = {run.params.nu:.3f}"
            if result.grips == "frictionless":
                dense = np.linspace(eps.min(), eps.max(), 200)
                curve = closed_form_forces(run.params, dense, SpecimenPlan(spec, spec))
                ax.plot(dense * 100, curve, color=color, ls=ls, label=label)
            else:
                sim = result.runs_simulated.get(run.method)
                if sim is not None:
                    ax.plot(eps * 100, sim[mask], color=color, ls=ls, marker=".", label=label + " (FEM)")
        axr.plot(eps * 100, (result.simulated - result.measured)[mask], "k.-", lw=0.8)
        axr.axhline(0.0, color="0.6", lw=0.8)
        ax.set_title(f"{spec.describe()}, {result.grips} grips", fontsize=10)
        ax.set_ylabel("axial force (N)")
        axr.set_ylabel(f"residual ({result.method}) N")
        axr.set_xlabel("nominal strain (%)")
        ax.grid(alpha=0.3)
        axr.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title or f"{result.params.model} fit: RMS {result.rms_force_N:.4g} N "
                 f"({100 * result.relative_rms:.2f} % of max force)", fontsize=11)
    fig.tight_layout()
    out = Path(path)
    try:
        with atomic_path(out, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return out
