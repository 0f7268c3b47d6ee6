"""A head as the Blender add-on drives it, without Blender: channel values → actuator pose → predicted skin, its
strain colours per vertex and the guard's verdict.

Blender holds every channel as a property, always with a value, where the daemon's channel vector has NaN for a
channel nobody addresses. A channel counts as *addressed* when it is animated (has an F-curve) or set away from its
rest value; the pose then follows the daemon's solve (``runtime/core/solve.py``): addressed ARKit channels are
solved to actuator values through the predictor's hidden-space inverse (from the neutral pose, so a frame's skin does
not depend on the frames visited before it), addressed groups set their members on top, and addressed actuators win
over both. Everything else stays at neutral.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from studio.head import Channel, StudioHead
from studio.skin import STRAIN_COLORS, STRAIN_EDGES, UNMEASURED, SkinView

#: Utilisation at which each strain colour is reached (between the studio's band edges); red from 1 on.
COLOR_KNOTS = (0.0, *(0.5 * (a + b) for a, b in zip((0.0, *STRAIN_EDGES[:-1]), STRAIN_EDGES, strict=True)), 1.0)


def _linear(c: tuple[int, int, int]) -> np.ndarray:
    """sRGB bytes → linear RGB floats (Blender's float colour attributes are linear)."""
    s = np.asarray(c, dtype=np.float64) / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


_KNOT_COLORS = np.array([_linear(STRAIN_COLORS[0]), *(_linear(c) for c in STRAIN_COLORS)])
_GREY = _linear(UNMEASURED)


@dataclass(frozen=True)
class SkinState:
    """One pose's predicted skin for Blender: vertex positions, per-vertex colour and the guard's verdict."""

    pose: np.ndarray  # (A,) actuator pose, SI
    positions: np.ndarray  # (V, 3) float32, metres
    colors: np.ndarray  # (V, 4) float32, linear RGBA
    utilisation: float  # largest strain utilisation over the kept skin (1 = the validated limit)
    passes: bool  # the guard's in-cycle check accepts the pose
    verdict: str  # the verdict in words


class HeadRig:
    """The predictor, the guard and the channel rules of one head, for the add-on's update handler."""

    def __init__(self, head: StudioHead) -> None:
        self.head = head
        self.view = SkinView(head)
        self.faces = self.view.faces.astype(np.int64)
        self.rest = np.asarray(head.predictor.predict(head.neutral), dtype=np.float32).copy()
        # Vertex ← measured triangles: mean of the utilisation of the kept triangles around each vertex.
        n_v = head.predictor.n_vertices
        kept = np.zeros(len(self.faces), dtype=bool)
        kept[self.view.kept] = True
        counts = np.zeros(n_v)
        np.add.at(counts, self.faces[kept].ravel(), 1.0)
        self._kept = kept
        self._counts = counts

    @classmethod
    def load(cls, config: str | Path) -> HeadRig:
        return cls(StudioHead.load(config))

    @property
    def channels(self) -> tuple[Channel, ...]:
        return self.head.channels

    def defaults(self) -> dict[str, float]:
        """Each channel's rest value (its property's default)."""
        return {c.name: float(c.neutral) for c in self.channels}

    def pose(self, addressed: Mapping[str, float]) -> np.ndarray:
        """Actuator pose (SI) of the addressed channels' values (config units; weights for ``arkit.*``)."""
        h = self.head
        unknown = [n for n in addressed if n not in h.by_name]
        if unknown:
            raise KeyError(f"unknown channel(s) {unknown} for head {h.spec.name!r}")
        p = h.neutral.copy()
        targets = {n: v for n, v in addressed.items() if h.by_name[n].kind == "target"}
        if targets:
            p, _ = h.solve_targets(targets, h.neutral)
        groups = {n: v for n, v in addressed.items() if h.by_name[n].kind == "group"}
        actuators = {n: v for n, v in addressed.items() if h.by_name[n].kind == "actuator"}
        return h.apply(h.apply(p, groups), actuators)

    def vertex_utilisation(self, u: np.ndarray) -> np.ndarray:
        """Strain utilisation per vertex from the per-triangle one (mean over its measured triangles; NaN where none
        is measured), so the colours are interpolated across the skin rather than patches per triangle."""
        acc = np.zeros(len(self._counts))
        np.add.at(acc, self.faces[self._kept].ravel(), np.repeat(u[self._kept], 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self._counts > 0, acc / self._counts, np.nan)

    def colors(self, u_vertex: np.ndarray) -> np.ndarray:
        """Linear RGBA per vertex: the studio's strain colours interpolated over utilisation, grey if unmeasured."""
        out = np.ones((len(u_vertex), 4), dtype=np.float32)
        ok = np.isfinite(u_vertex)
        u = np.clip(u_vertex[ok], 0.0, 1.0)
        for c in range(3):
            out[ok, c] = np.interp(u, COLOR_KNOTS, _KNOT_COLORS[:, c])
        out[~ok, :3] = _GREY
        return out

    def skin(self, p: np.ndarray) -> SkinState:
        """The predicted skin of actuator pose ``p`` (SI) with its colours and verdict."""
        p = np.asarray(p, dtype=np.float64)
        pos = np.asarray(self.head.predictor.predict(p), dtype=np.float32).copy()
        u_face, strain = self.view.utilisation(pos)
        u_vertex = self.vertex_utilisation(u_face)
        passes = bool(self.head.guard.check(p))
        return SkinState(p, pos, self.colors(u_vertex), float(np.nanmax(u_face)), passes,
                         self.view.verdict(p, strain, passes))

    def channel_values(self, p: np.ndarray) -> list[float]:
        """The actuator channels of pose ``p`` in config units, in head order (what the live link streams)."""
        return [float(x) for x in np.asarray(p) / self.head.scale]
