"""What a dataset run simulates: a pose problem maps actuator values to the skin's outer surface.

A :class:`ProblemSpec` is small and picklable (paths and parameters); each worker process builds the heavy
:class:`PoseProblem` from it once (:func:`problem_for`) and reuses it for every task. ``solve`` takes a warm-start
state (from the nearest solved pose) and returns the surface, the state to warm-start others from, and whether
the solver converged.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class PoseSolution:
    """One solved pose: outer-surface positions (V, 3) m, full solver state, convergence, iterations."""

    surface: np.ndarray
    state: np.ndarray | None
    converged: bool
    iterations: int
    message: str = ""


class PoseProblem(ABC):
    """The simulation behind a dataset: base surface, faces, and a warm-startable solve per pose."""

    @abstractmethod
    def base_surface(self) -> np.ndarray:
        """Outer-surface vertex positions (V, 3) of the neutral (rest) skin, metres."""

    @abstractmethod
    def faces(self) -> np.ndarray:
        """Outer-surface triangles (F, 3) indexing :meth:`base_surface`."""

    @abstractmethod
    def solve(self, p: np.ndarray, warm_state: np.ndarray | None, index: int | None = None) -> PoseSolution:
        """Solve one pose (actuator values, SI) from a warm-start state (None: from rest); ``index`` for logs."""

    def face_units(self) -> tuple[tuple[str, ...], np.ndarray | None]:
        """Names and offsets (U, V, 3) of expression face units on the surface, if the problem has them."""
        return (), None

    def surface_regions(self) -> tuple[tuple[str, ...], np.ndarray]:
        """Region names and the region index (V,) of every surface vertex (default: one region)."""
        return ("surface",), np.zeros(len(self.base_surface()), dtype=np.int32)

    def mesh_info(self) -> dict[str, Any]:
        """What was simulated, for reports: kind, element order, element and vertex counts (None: no elements)."""
        return {"kind": type(self).__name__, "element_order": None, "n_elements": None, "n_nodes": None,
                "n_surface_vertices": len(self.base_surface()), "n_surface_triangles": len(self.faces())}


class ProblemSpec(ABC):
    """A picklable recipe for a :class:`PoseProblem`; ``token`` identifies it for the per-worker cache."""

    @property
    @abstractmethod
    def token(self) -> str:
        """A string unique to this problem's content (paths and parameters)."""

    @abstractmethod
    def build(self) -> PoseProblem:
        """Construct the problem (runs once per worker process)."""

    def describe(self) -> dict[str, Any]:
        """JSON-able description stored in the dataset manifest."""
        return {"kind": type(self).__name__, "token": self.token}


_CACHE: dict[str, PoseProblem] = {}


def problem_for(spec: ProblemSpec) -> PoseProblem:
    """The problem of ``spec``, built once per process."""
    prob = _CACHE.get(spec.token)
    if prob is None:
        prob = spec.build()
        _CACHE.clear()
        _CACHE[spec.token] = prob
    return prob
