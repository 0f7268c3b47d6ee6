"""Compiling the in-cycle kernels (:mod:`models._skin_kernels`) ahead of the first daemon start
(``python -m models.kernels [HEAD]``, run by ``make install``): into numba's on-disk cache, and into an extension
module the control loop loads without importing numba (:mod:`models.kernels_aot`).

Whether they can run at all (they need numba) is :func:`models.kernel_support.kernels_available`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from models.kernel_support import kernels_available

if TYPE_CHECKING:
    from models.headspec import HeadSpec
    from models.predictor import SkinPredictor


def warm(head_path: str, ahead_of_time: bool = True) -> None:
    """Compile every kernel into numba's on-disk cache with the argument types a head's solver and guard use
    (``make install`` runs this, so the first daemon start does not spend seconds compiling), then, with
    ``ahead_of_time``, the loop's kernels into :mod:`models.kernels_aot`'s module (unless built for these sources
    already); nothing to do without numba."""
    if not kernels_available():
        return
    from models.headspec import load_head
    from models.predictor import SkinPredictor

    head = load_head(head_path)
    path = head.path("predictor")
    if path is None:
        return
    from models import kernels_aot

    examples: dict[str, tuple] = {}
    with kernels_aot.recording(examples):
        _run_kernels(head, SkinPredictor(path))
    if ahead_of_time and kernels_aot.module() is None and all(name in examples for name in kernels_aot.EXPORTS):
        kernels_aot.build(examples)


def _run_kernels(head: HeadSpec, sp: SkinPredictor) -> None:
    """Call every in-cycle kernel once as a head's skin solver, strain guard, clips and watch do (compiling them)."""
    from models.ksnn_solve import KsnnInverse
    from models.strain_guard import StrainGuard

    guard = StrainGuard.for_head(head, sp)  # compiles the reduced measure and the limit
    if guard is not None:
        from models.kernel_args import pack_constraints

        guard.check(0.5 * (guard.lo + guard.hi))
        guard.limit(guard.lo.copy(), 0.5 * (guard.lo + guard.hi))
        lo = np.array([a.min for a in head.actuators])  # and the control cycle's guard stage
        hi = np.array([a.max for a in head.actuators])
        guard.limit_constrained(0.5 * (lo + hi), lo.copy(), lo.copy(), lo, hi, pack_constraints(head))
    if sp.face_unit_offsets is not None:
        lo = np.maximum([a.min for a in head.actuators], sp.lo)
        hi = np.minimum([a.max for a in head.actuators], sp.hi)
        inv = KsnnInverse(sp.weights, sp.face_unit_offsets, lo=lo, hi=hi)  # compiles the solve
        inv.solve(np.zeros(inv.n_units), p_prev=0.5 * (lo + hi), max_iterations=2)
        inv.solve(np.zeros(inv.n_units), p_prev=0.5 * (lo + hi), max_iterations=2, measure=guard)  # and fused
        if guard is not None:  # and the control cycle's frame solve from channel values
            inv.frame_solve(2, 1e-6, 1e-3, guard)(np.full(inv.n_units, np.nan), 0.5 * (lo + hi))
    from models.kernel_args import bezier_sample_example, channel_targets_example, following_watch_example
    from models.kernels_aot import kernel

    kernel("bezier_sample")(*bezier_sample_example())  # a clip's Bezier channels, as the control cycle samples them
    kernel("following_watch")(*following_watch_example())  # the core's following-error watch
    kernel("channel_targets")(*channel_targets_example())  # and its channels → actuator targets


if __name__ == "__main__":
    import sys
    from pathlib import Path

    warm(sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).resolve().parents[1] / "heads/sample/head.toml"))
