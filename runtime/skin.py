"""Target-space channels solved through the learned skin: ``arkit.<faceUnit>`` weights → actuator values.

The weights define a target surface (base + Σ wᵢ Δᵢ, the face units stored in the predictor file); the hidden-space
inverse (``models.ksnn_solve``) finds the actuator values whose predicted skin matches it, warm-started from the
previous frame with temporal smoothness, within the head's limits and the predictor's trained range. The skin-strain
guard (:class:`models.strain_guard.StrainGuard`, its reduced in-cycle check) then checks the solution: a pose whose
strain measure leaves the material's validated range (default −20 % .. +50 %, ``docs/skin_guard.md``) is pulled back
toward the last accepted pose until it passes, or the last accepted pose is held. Telemetry carries the solve
residual, iterations, time and guard outcome. Imports only numpy, scipy and onnxruntime (via models).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from models.errors import SpecError
from models.headspec import HeadSpec
from models.ksnn_solve import KsnnInverse
from models.predictor import DEFAULT_STRAIN_RANGE, SkinPredictor
from models.strain_guard import StrainGuard, skin_number, skin_strain_range
from runtime.solve import SolveExtra, SolveResult, TargetSolver

log = logging.getLogger(__name__)

PREFIX = "arkit."


class SkinTargetSolver:
    """:class:`runtime.solve.TargetSolver` for ``arkit.*`` channels of a head with a skin predictor."""

    def __init__(self, head: HeadSpec, predictor: SkinPredictor | str | Path,
                 strain_range: tuple[float, float] = DEFAULT_STRAIN_RANGE, smoothness: float = (0.1e-3) ** 2,
                 max_iterations: int = 3, tol: float = 1e-6, strain_guard: StrainGuard | None = None,
                 xtol: float = 1e-3) -> None:
        sp = predictor if isinstance(predictor, SkinPredictor) else SkinPredictor(predictor)
        sp.check_against(head, require_full_range=False)
        if sp.face_unit_offsets is None or not sp.face_unit_names:
            raise SpecError(str(sp.path), "metadata likeness.face_units",
                            "the predictor carries no face units, so it cannot solve arkit.* channels")
        self.head = head
        self.predictor = sp
        self.names = sp.actuator_names
        self.units = {n: i for i, n in enumerate(sp.face_unit_names)}
        # Solutions stay where the head allows and the predictor was trained (no extrapolation).
        self.lo = np.maximum([a.min for a in head.actuators], sp.lo)
        self.hi = np.minimum([a.max for a in head.actuators], sp.hi)
        self.inverse = KsnnInverse(sp.weights, sp.face_unit_offsets, smoothness=smoothness, lo=self.lo, hi=self.hi)
        self.max_iterations = max_iterations  # per frame: the warm start carries the solve across frames
        self.tol = tol
        # A frame whose Gauss-Newton step moves no actuator by more than this fraction of its range is done: on the
        # sample performance at 500 Hz most frames then take one iteration, within 0.02° of running all of them.
        self.xtol = xtol
        self.neutral = np.array(head.neutral_pose)
        if strain_guard is None:
            strain_guard = StrainGuard(sp, np.clip(self.neutral, sp.lo, sp.hi), strain_range,
                                       names=tuple(a.name for a in head.actuators))
        elif strain_guard.predictor is not sp:
            raise ValueError("strain_guard must be built on the solver's predictor")
        self.strain_guard = strain_guard
        self.strain_range = strain_guard.strain_range
        self._accepted = self.neutral.copy()
        self._weights = np.zeros(len(self.units))
        # compile (or load) the fused solve-and-measure kernel now, never in a control cycle
        self.inverse.solve(self._weights, max_iterations=1, measure=strain_guard)

    @classmethod
    def from_head(cls, head: HeadSpec) -> SkinTargetSolver | None:
        """The solver for the head's ``paths.predictor``, or None when the head names none.

        A predictor file that is named but missing is a :class:`SpecError` (the daemon stops at start-up rather than
        silently dropping the ``arkit.*`` channels) unless ``[paths] predictor_optional = true``, which logs a warning
        and returns None.

        An optional ``[skin]`` table tunes it: ``strain_min`` / ``strain_max`` (validated range of the strain
        measure, default −0.2 / 0.5), ``radius_mm`` / ``band_mm`` / ``reference`` (the measure's neighbourhood,
        attachment band and reference surface, ``models.strain_guard``), ``smoothness_mm`` (RMS surface error,
        mm, that a full-range jump of one actuator costs, default 0.1) and ``iterations_per_frame`` (default 3).
        ``[paths] skin_guard`` names the attachment footprint of the skin (``likeness offline guard footprint``).
        """
        path = head.path("predictor")
        if path is None:
            return None
        if not Path(path).is_file():
            if head.predictor_optional:
                log.warning("%s: predictor file %s not found; running without the arkit.* target channels "
                            "([paths] predictor_optional = true)", head.source, path)
                return None
            raise SpecError(str(head.source), "paths.predictor",
                            f"predictor file not found: {path} (set [paths] predictor_optional = true to run "
                            "without its target channels)")
        cfg = dict(head.section("skin"))
        allowed = {"strain_min", "strain_max", "radius_mm", "band_mm", "reference", "smoothness_mm",
                   "iterations_per_frame"}
        for key in cfg:
            if key not in allowed:
                raise SpecError(str(head.source), f"skin.{key}", f"unknown key; allowed: {', '.join(sorted(allowed))}")

        lo, hi = skin_strain_range(head)
        smooth = skin_number(head, "smoothness_mm", 0.1)
        if smooth < 0:
            raise SpecError(str(head.source), "skin.smoothness_mm", "must not be negative", smooth)
        iters = cfg.get("iterations_per_frame", 3)
        if isinstance(iters, bool) or not isinstance(iters, int) or iters < 1:
            raise SpecError(str(head.source), "skin.iterations_per_frame", "must be a positive integer", iters)
        sp = SkinPredictor(path)
        sp.check_against(head, require_full_range=False)
        guard = StrainGuard.for_head(head, predictor=sp)
        return cls(head, sp, strain_range=(lo, hi), smoothness=(smooth * 1e-3) ** 2, max_iterations=iters,
                   strain_guard=guard)

    # ------------------------------------------------------------------ TargetSolver protocol
    def handles(self, channel: str) -> bool:
        return channel.startswith(PREFIX) and channel[len(PREFIX):] in self.units

    def channels(self) -> dict[str, str]:
        """The target channels this solver owns (unit: blendshape weight, 0..1)."""
        return {PREFIX + n: "weight" for n in self.units}

    def solve(self, targets: Mapping[str, float], current: Mapping[str, float]) -> SolveResult:
        """Actuator values (SI) for the addressed face-unit weights (unaddressed units count as 0)."""
        t0 = time.perf_counter()
        w = self._weights
        w[:] = 0.0
        for ch, value in targets.items():
            i = self.units.get(ch[len(PREFIX):]) if ch.startswith(PREFIX) else None
            if i is not None and np.isfinite(value):
                w[i] = min(max(float(value), 0.0), 1.0)
        g = self.strain_guard
        res = self.inverse.solve(w, p_prev=self._accepted, max_iterations=self.max_iterations, tol=self.tol,
                                 xtol=self.xtol, measure=g)
        strain = res.strain if res.strain is not None else g.measure(res.p)
        if g.passes(strain):  # the solution lies in the trained range by construction
            p, guard = res.p, "ok"
        else:
            p, guard, strain = self.guard(res.p)
        self._accepted = p
        extra: SolveExtra = {
            "skin_residual_mm": res.residual_rms * 1e3,
            "skin_iterations": res.iterations,
            "skin_solve_us": (time.perf_counter() - t0) * 1e6,
            "skin_strain": [round(strain[0], 4), round(strain[1], 4)],
            "skin_guard": guard,
        }
        return SolveResult({n: float(x) for n, x in zip(self.names, p, strict=True)}, extra)

    # ------------------------------------------------------------------ strain guard
    def strain(self, p: np.ndarray) -> tuple[float, float]:
        """The guard's reduced strain measure (min, max) at pose p."""
        return self.strain_guard.measure(p)

    def guard(self, p: np.ndarray, steps: int = 5) -> tuple[np.ndarray, str, tuple[float, float]]:
        """Accept p if the guard passes it; else the furthest passing point toward p from the last accepted pose
        (bisection), else hold the last accepted pose. Returns (pose, "ok"|"limited"|"held", strain)."""
        pose, outcome = self.strain_guard.limit(self._accepted, p, steps)
        return pose, outcome, self.strain_guard.measure(pose)

    def reset(self, positions: Mapping[str, float] | None = None) -> None:
        """Forget the warm start (on enable, fault, e-stop and reset): continue from ``positions`` or neutral."""
        self._accepted = self.neutral.copy()
        if positions:
            for i, n in enumerate(self.names):
                if n in positions and np.isfinite(positions[n]):
                    self._accepted[i] = min(max(float(positions[n]), self.lo[i]), self.hi[i])


def default_target_solvers(head: HeadSpec) -> list[TargetSolver]:
    """Target solvers a head's config asks for: the skin solver when ``paths.predictor`` exists."""
    skin = SkinTargetSolver.from_head(head)
    return [skin] if skin is not None else []
