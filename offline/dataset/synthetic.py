"""An analytic skin for exercising the dataset, training and runtime pipeline without the FEM.

A square sheet of surface vertices is pushed by one smooth bump per actuator; the displacement is the solution
of the per-coordinate implicit equation u + κ u³ = Σ_a g_a(X) φ(p̂_a) d_a (a stiffening skin), found by Newton's
method from the warm-start state, so warm starts matter and iteration counts are real. It is a test problem,
not a skin model: the FEM problem (``offline.dataset.fem_problem``) is what real datasets use.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline.dataset.problem import PoseProblem, PoseSolution, ProblemSpec


@dataclass(frozen=True)
class SyntheticSpec(ProblemSpec):
    """Parameters of the analytic sheet: ``grid``² vertices over ``size`` m, bump amplitude ``amplitude`` m."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    grid: int = 24
    size: float = 0.1
    amplitude: float = 0.004
    stiffening: float = 2.0e4
    seed: int = 0
    nonconverged_if_sum_above: float | None = None  # mark poses whose p̂ sum exceeds this as not converged
    crash_marker_dir: str | None = None  # test hook: the first solve of pose k in this folder kills its worker
    crash_indices: tuple[int, ...] = ()

    @property
    def token(self) -> str:
        return "synthetic-" + hashlib.sha1(json.dumps(self.__dict__, sort_keys=True, default=list).encode()
                                           ).hexdigest()[:16]

    def build(self) -> SyntheticSkin:
        return SyntheticSkin(self)


class SyntheticSkin(PoseProblem):
    """The analytic sheet of :class:`SyntheticSpec`."""

    def __init__(self, spec: SyntheticSpec) -> None:
        self.spec = spec
        g = spec.grid
        u, v = np.meshgrid(np.linspace(0, spec.size, g), np.linspace(0, spec.size, g), indexing="ij")
        self._base = np.stack([u.ravel(), v.ravel(), np.zeros(g * g)], axis=1)
        idx = np.arange(g * g).reshape(g, g)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        self._faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        rng = np.random.default_rng(spec.seed)
        n_act = len(spec.lo)
        centers = rng.uniform(0.15, 0.85, size=(n_act, 2)) * spec.size
        width = spec.size * rng.uniform(0.15, 0.3, size=n_act)
        d2 = ((self._base[None, :, :2] - centers[:, None, :]) ** 2).sum(-1)
        self._bump = np.exp(-d2 / (2 * width[:, None] ** 2))  # (A, V)
        dirs = rng.normal(size=(n_act, 3))
        dirs[:, 2] = np.abs(dirs[:, 2]) + 1.0
        self._dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        self._lo = np.asarray(spec.lo, dtype=float)
        self._hi = np.asarray(spec.hi, dtype=float)
        self._index_of: dict[bytes, int] = {}

    def base_surface(self) -> np.ndarray:
        return self._base.copy()

    def faces(self) -> np.ndarray:
        return self._faces.copy()

    def surface_regions(self) -> tuple[tuple[str, ...], np.ndarray]:
        """Each vertex in the region of the actuator whose bump moves it most (``bump_k``)."""
        return tuple(f"bump_{k}" for k in range(len(self._bump))), np.argmax(self._bump, axis=0).astype(np.int32)

    def mesh_info(self) -> dict[str, Any]:
        return {**super().mesh_info(), "kind": "analytic sheet (no elements)"}

    def forcing(self, p: np.ndarray) -> np.ndarray:
        x = (np.asarray(p, dtype=float) - self._lo) / (self._hi - self._lo)
        phi = np.sin(1.4 * (x - 0.3)) + 0.3 * x * x  # smooth, monotone-ish, nonlinear
        return self.spec.amplitude * np.einsum("a,av,ak->vk", phi, self._bump, self._dirs)

    def solve(self, p: np.ndarray, warm_state: np.ndarray | None, index: int | None = None) -> PoseSolution:
        spec = self.spec
        if spec.crash_marker_dir is not None and index in spec.crash_indices:
            import os
            from pathlib import Path

            marker = Path(spec.crash_marker_dir) / f"crashed_{index}"
            if not marker.exists():
                marker.write_text("1")
                os._exit(3)  # simulate a worker dying mid-solve (segfault, OOM kill)
        f = self.forcing(p)
        u = np.zeros_like(f) if warm_state is None else np.array(warm_state, dtype=float).reshape(f.shape)
        k = spec.stiffening
        it = 0
        converged = False
        for it in range(1, 51):  # noqa: B007 - reported
            r = u + k * u ** 3 - f
            if np.max(np.abs(r)) < 1e-13:
                converged = True
                break
            u -= r / (1.0 + 3.0 * k * u * u)
        x = (np.asarray(p, dtype=float) - self._lo) / (self._hi - self._lo)
        if spec.nonconverged_if_sum_above is not None and x.sum() > spec.nonconverged_if_sum_above:
            converged = False
        return PoseSolution(surface=self._base + u, state=u, converged=converged, iterations=it,
                            message="" if converged else "marked not converged")
