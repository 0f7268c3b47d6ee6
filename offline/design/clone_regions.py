"""Per-region figures of a face-cloning run: errors by surface region, which targets the mechanism reaches, the
free-skin gain of the thickness design, and the thickness change Δh (figures and a picture of the inner surface).

Regions are the skin's surface regions (:func:`offline.dataset.regions.label_surface`): outer vertices near a link
patch or the skull carry that set's name, the rest is ``free``. Thickness cannot move a link, so a target whose
error near the links stays above the goal after the actuation was optimized is out of the mechanism's reach; the
thickness design is judged on the free skin of the targets within reach.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline.dataset.regions import FREE

MM = 1e3


def region_errors(run, before: np.ndarray, after: np.ndarray) -> dict[str, dict[str, float]]:
    """Mean and max surface error (m) per region, before and after, from per-outer-vertex errors."""
    names, labels = run.face.skin.surface_regions()
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(names):
        sel = labels == k
        if not sel.any():
            continue
        out[name] = {"n_vertices": int(sel.sum()), "before_mean_m": float(before[sel].mean()),
                     "before_max_m": float(before[sel].max()), "after_mean_m": float(after[sel].mean()),
                     "after_max_m": float(after[sel].max())}
    return out


def region_summary(rows: list[dict[str, Any]], goal_mean_m: float) -> dict[str, Any]:
    """Which targets the mechanism reaches (error near links and skull after the actuation step at most
    ``goal_mean_m``) and, over those, the free-skin error with the uniform and the optimized skin."""
    reach, out_of_reach, changes = [], [], {}
    for r in rows:
        reg = r["regions"]
        attached = [v for n, v in reg.items() if n != FREE]
        n_att = sum(v["n_vertices"] for v in attached)
        near = sum(v["before_mean_m"] * v["n_vertices"] for v in attached) / max(n_att, 1)
        (reach if near <= goal_mean_m else out_of_reach).append(r["name"])
        if FREE in reg:
            b, a = reg[FREE]["before_mean_m"], reg[FREE]["after_mean_m"]
            changes[r["name"]] = {"free_before_mean_m": b, "free_after_mean_m": a,
                                  "relative_change": (a - b) / b if b > 0 else 0.0,
                                  "attached_before_mean_m": near}
    within = [changes[n] for n in reach if n in changes]
    before = float(np.mean([c["free_before_mean_m"] for c in within])) if within else float("nan")
    after = float(np.mean([c["free_after_mean_m"] for c in within])) if within else float("nan")
    return {"reachable_targets": reach, "out_of_reach_targets": out_of_reach,
            "criterion": f"mean surface error near links and skull after the actuation step <= {goal_mean_m} m",
            "free_region_before_mean_m": before, "free_region_after_mean_m": after,
            "free_region_reduction": (1.0 - after / before) if within and before > 0 else float("nan"),
            "worst_relative_change": max((c["relative_change"] for c in within), default=float("nan")),
            "per_target": changes}


def thickness_change(warp, face, h0: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Δh (m) at every free inner-surface node (the warp moves it along its thickness direction) and its |Δh|
    min / max / mean in mm."""
    free = np.setdiff1d(face.inner, face.locked)
    d = (warp.rest_positions(h) - warp.rest_positions(h0))[free]
    direction = np.asarray(warp.D @ np.ones(warp.n_samples)).reshape(-1, 3)[free]  # the warp's local direction
    sign = np.sign(np.einsum("ij,ij->i", d, direction))
    dh = np.linalg.norm(d, axis=1) * np.where(sign == 0, 1.0, sign)
    a = np.abs(dh) * MM
    return dh, {"abs_min_mm": float(a.min()), "abs_max_mm": float(a.max()), "abs_mean_mm": float(a.mean()),
                "min_mm": float(dh.min() * MM), "max_mm": float(dh.max() * MM), "n_nodes": int(free.size)}


def thickness_change_picture(path, run, warp, h0: np.ndarray, h: np.ndarray) -> None:
    """Front view of Δh on the inner surface (free nodes coloured, attachment nodes grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .mold import casting_frame

    face = run.face
    dh, stats = thickness_change(warp, face, h0, h)
    free = np.setdiff1d(face.inner, face.locked)
    locked = np.intersect1d(face.inner, face.locked)
    R = casting_frame(run.rest_outer, face.faces)
    c = run.rest_outer.mean(axis=0)
    X = np.asarray(face.mesh.nodes)
    uv_f = (X[free] - c) @ R[:2].T * MM
    uv_l = (X[locked] - c) @ R[:2].T * MM
    lim = max(float(np.abs(dh).max()) * MM, 1e-3)
    fig, ax = plt.subplots(figsize=(5.6, 5.0), constrained_layout=True)
    ax.scatter(uv_l[:, 0], uv_l[:, 1], s=4, c="0.75", label="attachments (locked)")
    sc = ax.scatter(uv_f[:, 0], uv_f[:, 1], s=7, c=dh * MM, cmap="RdBu_r", vmin=-lim, vmax=lim)
    ax.set_title(f"thickness change Δh on the inner surface: |Δh| mean {stats['abs_mean_mm']:.2f}, "
                 f"max {stats['abs_max_mm']:.2f} mm", fontsize=9)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.legend(fontsize=7, loc="lower left")
    fig.colorbar(sc, ax=ax, label="Δh (mm, + thicker)", shrink=0.8)
    fig.savefig(path, dpi=90)
    plt.close(fig)
