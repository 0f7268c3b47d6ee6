"""Arguments of the in-cycle kernels, built with numpy only (the loop process builds them without numba): the
constants of the frame solve packed into the four arrays :func:`models._skin_kernels.solve_values_measured`
unpacks, and example arguments of :func:`models._cycle_kernels.bezier_sample` and
:func:`models._cycle_kernels.following_watch` and :func:`models._cycle_kernels.channel_targets`."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from models.headspec import HeadSpec

#: A frame solve's step taken with a kept Gauss-Newton matrix longer than this (normalized actuator units: each range
#: is 1) forms the matrix afresh for the next iteration: the pose moved far from where it was formed
#: (:class:`models.ksnn_solve.HessianReuse`).
REFRESH_STEP = 0.02
#: A damped step that does not lower the objective (or a damped matrix that is not positive definite) is tried again
#: with the damping raised tenfold, and at least to this fraction of the Gauss-Newton matrix's mean diagonal: a
#: damping far below the matrix's scale changes nothing in the step, and each try costs a residual (the tries of a
#: frame that starts at the box's edge used to climb through six such values).
DAMPING_JUMP = 1e-3


def pack_frame_args(solve: tuple, measure: tuple, guard: tuple | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The constants of a frame solve (``KsnnInverse.kernel_arrays()`` + max iterations, tol, xtol), of the
    reduced measure (``StrainGuard.kernel_arrays()``) and of the guard's search when the solution leaves the strain
    range (``guard``: the guard's input scale and shift, strain min and max, bisections; None: not guarded) packed
    into four arrays, the layout :func:`models._skin_kernels.solve_values_measured` unpacks: a call then passes 10
    arguments instead of 40, and the dispatcher's per-argument typing (about 0.1 µs each, a few times that when its
    caches are cold) shrinks with them."""
    (lo, hi, scale_in, const_b, e, M, q0, QdT, lam_s, W1, b1, _W1b, Rb, Rm, xlo, xhi, mid, ihalf, mu, max_iterations,
     tol, xtol) = solve
    Q, E, ge0, tri, C, idet, S_ptr, S_idx, S_w = measure
    g_scale, g_shift, s_min, s_max, steps = (np.ones(len(lo)), np.zeros(len(lo)), 0.0, 0.0, -1) if guard is None \
        else guard
    f64 = np.concatenate([np.ravel(np.asarray(a, dtype=np.float64)) for a in (
        lo, hi, scale_in, xlo, xhi, mid, ihalf, e, M, q0, QdT, W1, b1, Rb, Rm, C, idet, S_w,
        [const_b, lam_s, mu, tol, xtol], g_scale, g_shift, [s_min, s_max])])
    f32 = np.concatenate([np.ravel(np.asarray(a, dtype=np.float32)) for a in (Q, E, ge0)])
    i64 = np.concatenate([np.asarray(S_ptr, dtype=np.int64), np.asarray(S_idx, dtype=np.int64),
                          np.ravel(np.asarray(tri, dtype=np.int64))])
    dims = np.array([len(lo), len(e), Rb.shape[2], len(idet), len(S_ptr), len(S_idx), E.shape[2], int(max_iterations),
                     int(steps), Rb.shape[1], Rm.shape[1], Q.shape[1]], dtype=np.int64)
    return f64, f32, i64, dims


def bezier_sample_example() -> tuple:
    """Arguments of the types :class:`runtime.compiled.CompiledClip` passes (read-only clip arrays, the writable
    slot indices and values a cycle computes), for compiling ahead of time: one curve of one segment, x(s) = y(s) =
    s, sampled at its middle (slots: pad, hold, two keys; coefficient rows: hold, segment, last key)."""
    ro = []
    for a in (np.array([0], np.int64), np.array([-1], np.int64), np.array([0.0]), np.array([1.0]),
              np.array([[0.0] * 8, [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0] * 8]),
              np.array([0.0, 0.0, 0.0, 1.0]), np.array([1.0, 1.0, 1.0, 1.0])):
        a.flags.writeable = False
        ro.append(a)
    bez, bez_row, first, last, coef, slot_t, slot_dt = ro
    return (0.5, np.array([2], np.int64), bez, bez_row, first, last, coef, slot_t, slot_dt, np.zeros(1))


def following_watch_example() -> tuple:
    """Arguments of the types :func:`runtime.core.watch.check_following` passes: three posted rows of two actuators
    on two buses, their measured positions, the buses' feedback ages and every limit, at t = 1 s."""
    posted = np.array([[0.0, 0.1], [0.0, 0.2], [np.nan, np.nan]])
    return (posted, np.array([0.05, 0.5]), np.array([0, 1], np.int64), np.array([0.001, 0.002]), np.array([0.01, 0.01]),
            np.array([0.2, 0.2]), np.array([0.5, 0.5]), np.zeros(2), np.full(2, np.nan), np.zeros(2), 1.0)


def channel_targets_example() -> tuple:
    """Arguments of the types :func:`runtime.core.solve.to_targets` passes: three channels (two actuators, one group
    of both), the targets to fill, the map's group and actuator arrays."""
    return (np.array([0.1, np.nan, 0.2]), np.full(2, np.nan), np.array([2, 2], np.int64), np.array([0, 1], np.int64),
            np.array([1.0, -1.0]), np.array([1.0, 1.0]))


def pack_constraints(head: HeadSpec) -> tuple[np.ndarray, np.ndarray]:
    """A head's actuator groups as :func:`models._cycle_kernels.constrain` reads them, the groups
    :class:`runtime.safety.SafetyFilter` applies ("together" and "mirror" groups with their gains, groups with a
    ``max_spread``). Ints: the counts of each kind, the together groups' offsets (CSR) and members, the coupled
    groups' offsets and members; floats: the together gains (one per member), then each coupled group's spread."""
    index = {n: i for i, n in enumerate(head.actuator_names)}
    tog = [g for g in head.groups if g.kind in ("together", "mirror")]
    cp = [g for g in head.groups if g.kind not in ("together", "mirror") and g.max_spread is not None]
    tog_ptr = np.cumsum([0] + [len(g.actuators) for g in tog])
    cp_ptr = np.cumsum([0] + [len(g.actuators) for g in cp])
    ints = [len(tog), len(cp), *tog_ptr, *(index[m] for g in tog for m in g.actuators), *cp_ptr,
            *(index[m] for g in cp for m in g.actuators)]
    floats = [float(x) for g in tog for x in g.gains] + [float(g.max_spread) for g in cp]
    return np.array(ints, dtype=np.int64), np.array(floats, dtype=np.float64)
