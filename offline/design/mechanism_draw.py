"""A picture of a mechanism over the face: its bodies, joints and rods in a front and a side view, drawn from the model.

Each body is drawn as lines from its origin to the points it carries (joint anchors, rod ends), each rod as a line
between its ends, joints as markers, attachment links' frames as dots with their names; the skin's nodes (when the
mesh is given) as a faint cloud behind. Poses after the first are drawn over the neutral one, so a picture shows how
the linkages move.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from models.atomic import atomic_path
from models.mechanism import Mechanism

#: (horizontal, vertical) head-frame axes of the two views: front (x, y) and the left side (z, y).
VIEWS = (("front", 0, 1), ("side", 2, 1))


def _segments(mech: Mechanism, T: Mapping[str, np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Body lines, rod lines (each a (2, 3) array in the posed head frame) and the joint anchors (n, 3)."""
    spec = mech.spec

    def at(body: str, p: np.ndarray) -> np.ndarray:
        return T[body][:3, :3] @ p + T[body][:3, 3]

    bodies, rods, joints = [], [], []
    for j in spec.joints.values():
        for b in (j.parent, j.child):
            if b != spec.ground:
                bodies.append(np.array([at(b, spec.bodies[b].origin), at(b, j.anchor)]))
        joints.append(at(j.child, j.anchor))
    for c in spec.couplers.values():
        if c.kind == "rod":
            rods.append(np.array([at(c.a, c.a_point), at(c.b, c.b_point)]))
            for b, p in ((c.a, c.a_point), (c.b, c.b_point)):
                if b != spec.ground:
                    bodies.append(np.array([at(b, spec.bodies[b].origin), at(b, p)]))
    return bodies, rods, np.array(joints) if joints else np.zeros((0, 3))


def draw_mechanism(mech: Mechanism, out: Path, poses: Sequence[Mapping[str, float]] = ({},),
                   skin_nodes: np.ndarray | None = None, title: str = "") -> Path:
    """Write a PNG of ``mech`` at each of ``poses`` (SI actuator values; the first drawn solid) atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 7))
    for ax, (name, h, v) in zip(axes, VIEWS, strict=True):
        if skin_nodes is not None and len(skin_nodes):
            ax.scatter(skin_nodes[:, h], skin_nodes[:, v], s=0.3, color="0.85", zorder=0)
        for k, pose in enumerate(poses):
            T = mech.body_transforms(pose)
            bodies, rods, joints = _segments(mech, T)
            alpha, ls = (1.0, "-") if k == 0 else (0.6, "--")
            for s in bodies:
                ax.plot(s[:, h], s[:, v], color="tab:blue", lw=1.6, alpha=alpha, ls=ls)
            for s in rods:
                ax.plot(s[:, h], s[:, v], color="tab:orange", lw=1.2, alpha=alpha, ls=ls)
            if len(joints):
                ax.scatter(joints[:, h], joints[:, v], s=12, color="k", alpha=alpha, zorder=3)
            for link in mech.spec.links:
                o = T[link][:3, :3] @ mech.spec.bodies[link].origin + T[link][:3, 3]
                ax.scatter([o[h]], [o[v]], s=28, color="tab:red", alpha=alpha, zorder=4)
                if k == 0:
                    ax.annotate(link, (o[h], o[v]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_aspect("equal")
        ax.set_title(f"{name} view (m)")
        ax.set_xlabel("x (head's left)" if h == 0 else "z (forward)")
        ax.set_ylabel("y (up)")
    axes[1].invert_xaxis()  # the face looks left in the side view
    fig.suptitle(title or f"mechanism {mech.spec.name}: bodies (blue), rods (orange), joints (black), links (red)")
    fig.tight_layout()
    with atomic_path(out, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return out
