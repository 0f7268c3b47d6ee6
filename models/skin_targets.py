"""A head's ARKit target space: face-unit weights → actuator values through the skin predictor's hidden-space inverse.

What the daemon's target solver, the offline strain checks and the studio share: the face units the predictor carries
(``arkit.<unit>`` channels, weights 0..1), the inverse (:class:`models.ksnn_solve.KsnnInverse`) bounded by the head's
limits and the predictor's trained range (no extrapolation), the ``[skin]`` solve settings and the skin-strain guard.
:func:`skin_targets_for_head` reads them from a head config; the daemon adds warm starts and the guard stage.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.errors import SpecError
from models.headspec import HeadSpec
from models.ksnn_solve import KsnnInverse
from models.predictor import DEFAULT_STRAIN_RANGE, SkinPredictor
from models.strain_guard import StrainGuard, skin_number, skin_strain_range

log = logging.getLogger(__name__)

#: Channel prefix of the face-unit targets.
PREFIX = "arkit."
#: Keys of the head's ``[skin]`` table.
SKIN_KEYS = frozenset({"strain_min", "strain_max", "radius_mm", "band_mm", "reference", "smoothness_mm",
                       "iterations_per_frame", "matrix_rank"})


@dataclass(frozen=True)
class SkinTargets:
    """The target space of one head: ``units`` maps face-unit name → weight index; ``max_iterations`` and ``tol``
    are the per-frame Gauss-Newton settings; ``lo``/``hi`` bound the solutions (SI, the head's actuator order)."""

    head: HeadSpec
    predictor: SkinPredictor
    units: dict[str, int]
    inverse: KsnnInverse
    lo: np.ndarray
    hi: np.ndarray
    max_iterations: int
    tol: float
    strain_guard: StrainGuard

    def channels(self) -> dict[str, str]:
        """The target channels (unit: blendshape weight, 0..1)."""
        return {PREFIX + n: "weight" for n in self.units}

    def weights(self, targets: Mapping[str, float]) -> np.ndarray:
        """The face-unit weight vector of ``arkit.*`` channel values (clipped to 0..1; others and non-finite
        values ignored, unaddressed units 0)."""
        w = np.zeros(len(self.units))
        for ch, value in targets.items():
            i = self.units.get(ch[len(PREFIX):]) if ch.startswith(PREFIX) else None
            if i is not None and np.isfinite(value):
                w[i] = min(max(float(value), 0.0), 1.0)
        return w


def skin_targets(head: HeadSpec, predictor: SkinPredictor | str | Path,
                 strain_range: tuple[float, float] = DEFAULT_STRAIN_RANGE, smoothness: float = (0.1e-3) ** 2,
                 max_iterations: int = 3, tol: float = 1e-6, strain_guard: StrainGuard | None = None,
                 matrix_rank: int | None = None) -> SkinTargets:
    """The target space of ``head`` on ``predictor`` (which must carry face units); ``smoothness`` is the cost
    (m², as RMS surface error squared) of a full-range jump of one actuator between frames; ``matrix_rank`` the
    inverse's Gauss-Newton matrix rank per axis (:class:`models.ksnn_solve.KsnnInverse`; None: exact)."""
    sp = predictor if isinstance(predictor, SkinPredictor) else SkinPredictor(predictor)
    sp.check_against(head, require_full_range=False)
    if sp.face_unit_offsets is None or not sp.face_unit_names:
        raise SpecError(str(sp.path), "metadata likeness.face_units",
                        "the predictor carries no face units, so it cannot solve arkit.* channels")
    lo = np.maximum([a.min for a in head.actuators], sp.lo)
    hi = np.minimum([a.max for a in head.actuators], sp.hi)
    inverse = KsnnInverse(sp.weights, sp.face_unit_offsets, smoothness=smoothness, lo=lo, hi=hi,
                          matrix_rank=matrix_rank)
    if strain_guard is None:
        strain_guard = StrainGuard(sp, np.clip(np.array(head.neutral_pose), sp.lo, sp.hi), strain_range,
                                   names=tuple(a.name for a in head.actuators))
    elif strain_guard.predictor is not sp:
        raise ValueError("strain_guard must be built on the solver's predictor")
    units = {n: i for i, n in enumerate(sp.face_unit_names)}
    return SkinTargets(head, sp, units, inverse, lo, hi, max_iterations, tol, strain_guard)


def skin_targets_for_head(head: HeadSpec, session: bool = True) -> SkinTargets | None:
    """The target space of the head's ``paths.predictor`` with its ``[skin]`` settings, or None when it names none.

    A predictor file that is named but missing is a :class:`SpecError` unless ``[paths] predictor_optional = true``,
    which logs a warning and returns None. The ``[skin]`` table: ``strain_min`` / ``strain_max`` (validated range of
    the strain measure, default −0.2 / 0.5), ``radius_mm`` / ``band_mm`` / ``reference`` (the measure's
    neighbourhood, attachment band and reference surface, ``models.strain_guard``), ``smoothness_mm`` (RMS surface
    error, mm, that a full-range jump of one actuator costs, default 0.1), ``iterations_per_frame`` (default 3) and
    ``matrix_rank`` (the rank per axis of the frame solve's Gauss-Newton matrix, a positive integer; default, or at
    least the predictor's output rank: exact Gauss-Newton; fewer rows make a step's model cheaper, the minimizer
    unchanged; fewer than the head's actuators lose directions the steps need, which is logged as a warning).
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
    for key in head.section("skin"):
        if key not in SKIN_KEYS:
            raise SpecError(str(head.source), f"skin.{key}", f"unknown key; allowed: {', '.join(sorted(SKIN_KEYS))}")
    lo, hi = skin_strain_range(head)
    smooth = skin_number(head, "smoothness_mm", 0.1)
    if smooth < 0:
        raise SpecError(str(head.source), "skin.smoothness_mm", "must not be negative", smooth)
    iters = head.section("skin").get("iterations_per_frame", 3)
    if isinstance(iters, bool) or not isinstance(iters, int) or iters < 1:
        raise SpecError(str(head.source), "skin.iterations_per_frame", "must be a positive integer", iters)
    rank = head.section("skin").get("matrix_rank")
    if rank is not None and (isinstance(rank, bool) or not isinstance(rank, int) or rank < 1):
        raise SpecError(str(head.source), "skin.matrix_rank", "must be a positive integer", rank)
    if rank is not None and rank < len(head.actuators):
        log.warning("%s: [skin] matrix_rank = %d is below the head's %d actuators: the frame solve's steps lose "
                    "directions they need and end frames with larger errors (docs/predictor.md)", head.source, rank,
                    len(head.actuators))
    sp = SkinPredictor(path, session=session)  # session=False: onnxruntime loaded on the first full pass only
    sp.check_against(head, require_full_range=False)
    guard = StrainGuard.for_head(head, predictor=sp)
    return skin_targets(head, sp, strain_range=(lo, hi), smoothness=(smooth * 1e-3) ** 2, max_iterations=iters,
                        strain_guard=guard, matrix_rank=rank)
