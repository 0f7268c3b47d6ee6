"""The full skin-strain check of telemetry in NumPy alone, from arrays the daemon's strain guard already holds.

The API server confirms the loop's reduced strain check on every commanded pose with the full one (every vertex of
the predicted surface, every kept triangle). Done with the guard itself that needs onnxruntime (the predictor's
session, ~44 MB resident) and scipy (the smoothing matrix), which kept the resting server process above its memory
goal. The same numbers come from the guard's arrays: the KSNN forward pass over every vertex is two small matrix
products (:meth:`models.predictor.KsnnWeights.offsets`), the smoothing a sparse product written here with
``np.bincount``. :meth:`FullStrainCheck.of` takes them from the guard the daemon built (the loop process has it
anyway); the object pickles with NumPy arrays only, travels to the server in its start-up spec, and its
unpickling imports neither onnxruntime nor scipy. The reduced check it is compared with is the guard's own, run in
NumPy on a copy of the guard without its predictor and surface (:meth:`check`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from models.strain_guard import principal_strains, triangle_metric

if TYPE_CHECKING:
    from models.predictor import KsnnWeights
    from models.strain_guard import StrainGuard


@dataclass(frozen=True)
class FullStrainCheck:
    """The full measure (smallest smoothed ε_min, largest smoothed ε_max) of a pose, and the verdicts around it."""

    weights: KsnnWeights  # the predictor's KSNN (NumPy arrays)
    lo: np.ndarray  # the predictor's trained range (SI, actuator order): poses are clamped to it
    hi: np.ndarray
    base: np.ndarray  # (V, 3) rest surface
    faces: np.ndarray  # (T, 3)
    g0: np.ndarray  # (T, 3) metric of the reference surface the strain is measured against
    rows: np.ndarray  # (nnz,) smoothing matrix, kept triangle of each entry
    cols: np.ndarray  # (nnz,) its triangle
    vals: np.ndarray  # (nnz,) its weight
    n_kept: int
    strain_range: tuple[float, float]
    reduced: StrainGuard  # the guard without predictor and surface: its reduced check in NumPy

    @classmethod
    def of(cls, guard: StrainGuard) -> FullStrainCheck:
        """The check of ``guard`` (built where the guard was: the arrays are copied out of it)."""
        smooth = guard.surface.smooth.tocoo()
        light = copy.copy(guard)
        light.predictor = None  # type: ignore[assignment]  # the onnxruntime session stays behind
        light.surface = None  # type: ignore[assignment]  # and the scipy matrices
        light.compiled = False  # the ahead-of-time kernels are the loop's; NumPy gives the same verdict
        return cls(guard.weights, guard.lo.copy(), guard.hi.copy(), guard.surface.rest, guard.surface.faces,
                   triangle_metric(np.asarray(guard.reference, dtype=np.float64), guard.surface.faces),
                   smooth.row.astype(np.int64), smooth.col.astype(np.int64), smooth.data.astype(np.float64),
                   int(smooth.shape[0]), guard.strain_range, light)

    def field(self, q: np.ndarray) -> np.ndarray:
        """Smoothed principal strains (K, 2) at the kept triangles of the surface predicted at pose ``q`` (SI,
        clamped to the trained range)."""
        p = np.clip(np.asarray(q, dtype=np.float64), self.lo, self.hi)
        pos = self.base + self.weights.offsets(p)
        eps = principal_strains(self.g0, triangle_metric(pos, self.faces))
        # one column at a time: a gather and a weighted bincount on contiguous arrays (half the time of both at once)
        return np.stack([np.bincount(self.rows, eps[:, k][self.cols] * self.vals, self.n_kept) for k in range(2)],
                        axis=1)

    def full(self, q: np.ndarray) -> tuple[float, float]:
        """The full measure of pose ``q``: (smallest smoothed ε_min, largest smoothed ε_max)."""
        f = self.field(q)
        return float(f[:, 0].min()), float(f[:, 1].max())

    def passes(self, strain: tuple[float, float]) -> bool:
        """Whether a measure lies within the skin's validated strain range."""
        return self.strain_range[0] <= strain[0] and strain[1] <= self.strain_range[1]

    def in_range(self, q: np.ndarray) -> bool:
        """Whether ``q`` lies in the predictor's trained range (the model cannot vouch for a pose outside it)."""
        return self.reduced.in_range(q)

    def check(self, q: np.ndarray) -> bool:
        """The loop's in-cycle (reduced) verdict on ``q``, in NumPy."""
        return self.reduced.check(np.asarray(q, dtype=np.float64))
