"""The predicted skin of a pose, coloured by the strain the guard evaluates, and the guard's verdict in words.

Each outer-surface triangle gets the guard's smoothed principal strains (``StrainGuard.surface.field``) and a
*utilisation* u = max(ε_min / strain_min, ε_max / strain_max): 0 at rest, 1 at the validated limit. Triangles are
sorted into colour bands (green well inside the range through yellow and orange to red beyond it; grey where the
measure leaves triangles out beside the rigid attachments), one mesh per band, so the browser draws a colour map
with plain single-colour meshes. The error map of an exact FEM pose uses the same bands on a 0–4 mm scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from studio.head import StudioHead

RGB = tuple[int, int, int]

#: Strain bands: upper utilisation edge and colour; the last band (u >= 1) is past the validated range.
STRAIN_EDGES = (0.5, 0.7, 0.85, 1.0)
STRAIN_COLORS: tuple[RGB, ...] = ((46, 160, 67), (150, 195, 60), (235, 200, 40), (240, 130, 30), (215, 35, 35))
#: Colour of triangles the measure leaves out (beside rigid attachments).
UNMEASURED: RGB = (165, 165, 170)
#: Error map bands (mm): 0–1, 1–2, 2–3, 3–4, above 4.
ERROR_EDGES_MM = (1.0, 2.0, 3.0, 4.0)
ERROR_COLORS: tuple[RGB, ...] = ((40, 90, 200), (40, 170, 190), (120, 190, 70), (240, 170, 40), (215, 35, 35))


def band_of(values: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Band index of each value: 0 below ``edges[0]`` … ``len(edges)`` at or above the last edge; NaN → -1."""
    v = np.asarray(values, dtype=np.float64)
    out = np.searchsorted(np.asarray(edges, dtype=np.float64), v, side="right")
    out[~np.isfinite(v)] = -1
    return out


def faces_by_band(faces: np.ndarray, bands: np.ndarray, n_bands: int) -> list[np.ndarray]:
    """The triangles of each band (band -1, unmeasured, comes last)."""
    out = [faces[bands == b] for b in range(n_bands)]
    out.append(faces[bands < 0])
    return out


@dataclass(frozen=True)
class SkinFrame:
    """One pose's predicted surface and its strain picture."""

    positions: np.ndarray  # (V, 3) float32, metres
    band_faces: list[np.ndarray]  # per strain band, then the unmeasured triangles
    strain: tuple[float, float]  # (smallest ε_min, largest ε_max) of the smoothed measure over the kept skin
    utilisation: float  # largest u over the kept skin
    passes: bool  # the guard's in-cycle check accepts the pose
    verdict: str  # the verdict in words
    face_utilisation: np.ndarray  # per triangle u (NaN where unmeasured)


class SkinView:
    """Predicts the skin of actuator poses and describes them against the guard's validated range."""

    def __init__(self, head: StudioHead) -> None:
        self.head = head
        self.guard = head.guard
        self.faces = np.asarray(head.predictor.faces, dtype=np.uint32)
        self.kept = self.guard.surface.kept
        lo, hi = self.guard.strain_range
        self._inv = np.array([1.0 / lo, 1.0 / hi])
        self._out = np.empty((head.predictor.n_vertices, 3), dtype=np.float32)

    def utilisation(self, positions: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
        """Per-triangle utilisation (NaN where unmeasured) and the measure's extremes for one surface."""
        field = self.guard.surface.field(np.asarray(positions, dtype=np.float64), self.guard.reference)  # (K, 2)
        u = np.full(len(self.faces), np.nan)
        u[self.kept] = np.max(field * self._inv, axis=1)
        return u, (float(field[:, 0].min()), float(field[:, 1].max()))

    def frame(self, p: np.ndarray) -> SkinFrame:
        """The predicted skin of actuator pose ``p`` (SI, head order) with its strain bands and verdict."""
        p = np.asarray(p, dtype=np.float64)
        pos = self.head.predictor.predict(p).copy()
        u, strain = self.utilisation(pos)
        bands = band_of(u, STRAIN_EDGES)
        passes = bool(self.guard.check(p))
        umax = float(np.nanmax(u))
        return SkinFrame(pos, faces_by_band(self.faces, bands, len(STRAIN_COLORS)), strain, umax, passes,
                         self.verdict(p, strain, passes), u)

    def verdict(self, p: np.ndarray, strain: tuple[float, float], passes: bool) -> str:
        """The guard's decision on pose ``p`` in words, with the measure against the validated range."""
        lo, hi = self.guard.strain_range
        measure = f"strain {strain[0] * 100:+.1f} % … {strain[1] * 100:+.1f} % (validated {lo * 100:+.0f} % … " \
                  f"{hi * 100:+.0f} %)"
        if not self.guard.in_range(p):
            return f"Refused: outside the predictor's trained range (the guard cannot vouch for it). {measure}"
        if passes:
            return f"Accepted: within the skin's validated range. {measure}"
        reasons = []
        if strain[1] > hi:
            reasons.append(f"stretch {strain[1] * 100:+.1f} % beyond {hi * 100:+.0f} %")
        if strain[0] < lo:
            reasons.append(f"compression {strain[0] * 100:+.1f} % beyond {lo * 100:+.0f} %")
        why = " and ".join(reasons) or "near the limit on a guarded patch"
        return f"Refused: {why}; the daemon would limit or hold this pose. {measure}"

    def error_bands(self, exact: np.ndarray, predicted: np.ndarray) -> tuple[list[np.ndarray], float, float]:
        """Error-map bands of the predictor against an exact surface: per band its triangles, and the largest and
        mean vertex error (mm)."""
        err = np.linalg.norm(np.asarray(predicted, dtype=np.float64) - np.asarray(exact, dtype=np.float64), axis=1)
        err_mm = err * 1e3
        per_face = err_mm[self.faces.astype(np.intp)].mean(axis=1)
        bands = band_of(per_face, ERROR_EDGES_MM)
        return faces_by_band(self.faces, bands, len(ERROR_COLORS))[:-1], float(err_mm.max()), float(err_mm.mean())
