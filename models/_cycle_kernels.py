"""Compiled inner loops of the control cycle's own stages (numba): a clip's Bezier sampling and the following-error
watch, for the control loop's every cycle.

:meth:`runtime.compiled.CompiledClip.sample` evaluates every Bezier channel by the safeguarded Newton iteration of
:func:`models.clip._bezier_eval`. In numpy that iteration runs on all channels in lockstep, a few dozen array calls per
cycle whose interpreter overhead is most of the clip's cost; compiled, each channel runs the scalar loop itself
(:func:`models.clip._bezier_eval`, compiled as it is: no fused multiply-add, numba contracts only under
``fastmath``), so the values keep the bits of :meth:`models.clip.Clip.sample`. Compiled on first use and cached on
disk, and ahead of time with the skin kernels (:mod:`models.kernels_aot`). The watch's numpy version stays in
:mod:`runtime.core.watch` as the reference the tests compare against.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from models import clip

#: :func:`models.clip._bezier_eval` itself, compiled: the operations of the scalar loop, in its order.
_bezier_eval = njit(cache=True, fastmath=False)(clip._bezier_eval)


@njit(cache=True, fastmath=False)
def bezier_sample(t: float, i: np.ndarray, bez: np.ndarray, bez_row: np.ndarray, bez_first: np.ndarray,
                  bez_last: np.ndarray, coef: np.ndarray, slot_t: np.ndarray, slot_dt: np.ndarray,
                  vals: np.ndarray) -> None:
    """Overwrite ``vals[c]`` of each Bezier curve ``c = bez[k]`` strictly inside its key range (``bez_first[k] < t <
    bez_last[k]``) with its value at time ``t``: slot ``i[c]``'s segment (coefficients ``coef[i[c] + bez_row[k]]``:
    time a, b, c, d, value a, b, c, d), solved for x(s) = t from the linear guess by
    :func:`models.clip._bezier_eval`. The arrays are :class:`runtime.compiled.CompiledClip`'s."""
    for k in range(bez.shape[0]):
        if not (bez_first[k] < t and bez_last[k] > t):
            continue
        c = bez[k]
        j = i[c]
        r = coef[j + bez_row[k]]
        seg = (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7])
        vals[c] = _bezier_eval(seg, t, (t - slot_t[j]) / slot_dt[j])


@njit(cache=True, fastmath=False)
def following_watch(posted: np.ndarray, measured: np.ndarray, bus_of: np.ndarray, ages: np.ndarray,
                    late_s: np.ndarray, max_error: np.ndarray, error_time_s: np.ndarray, peak: np.ndarray,
                    over_since: np.ndarray, error: np.ndarray, t: float) -> int:
    """:func:`runtime.core.watch.check_following`'s arithmetic in one call: per actuator ``j`` the distance of
    ``measured[j]`` outside the span of the commands ``posted[:, j]`` (NaN rows skipped; 0 where nothing was posted
    or measured, and where its bus ``bus_of[j]`` is late, ``ages > late_s``; -1: no bus) into ``error``, the running
    maximum into ``peak``, and since when it is beyond ``max_error`` into ``over_since`` (NaN: within). Returns the
    first actuator beyond its limit for ``error_time_s`` at ``t``, or -1."""
    n = measured.shape[0]
    any_over = False
    for j in range(n):
        lo = np.nan
        hi = np.nan
        for r in range(posted.shape[0]):
            v = posted[r, j]
            if v == v:  # fmin / fmax: a NaN row (not yet posted) is skipped
                if not lo <= v:
                    lo = v
                if not hi >= v:
                    hi = v
        m = measured[j]
        a = lo - m
        b = m - hi
        e = a if b != b or a >= b else b  # fmax(a, b)
        if not e >= 0.0:  # fmax(e, 0): NaN (nothing posted or measured) is 0
            e = 0.0
        k = bus_of[j]
        if k >= 0 and ages[k] > late_s[k]:
            e = 0.0
        error[j] = e
        if e > peak[j]:
            peak[j] = e
        if e > max_error[j]:
            any_over = True
    if not any_over:
        over_since[:] = np.nan
        return -1
    due = -1
    for j in range(n):
        if error[j] > max_error[j]:
            if over_since[j] != over_since[j]:
                over_since[j] = t
            if due < 0 and t - over_since[j] >= error_time_s[j]:
                due = j
        else:
            over_since[j] = np.nan
    return due


@njit(cache=True, fastmath=False)
def constrain(x: np.ndarray, current: np.ndarray, lo: np.ndarray, hi: np.ndarray, groups_i: np.ndarray,
              groups_f: np.ndarray, out: np.ndarray) -> None:
    """:meth:`runtime.safety.SafetyFilter.constrain` into ``out``: holds (NaN) filled from ``current``, each
    "together" group set to its gain-scaled mean, each coupled group's spread scaled down to its limit, then clipped
    to ``[lo, hi]``; the same operations in the same order (the same values; a group of 8 or more members may
    differ in the last bit, where numpy sums pairwise). The groups are packed by
    :func:`models.kernel_args.pack_constraints`."""
    n = x.shape[0]
    for i in range(n):
        v = x[i]
        out[i] = v if np.isfinite(v) else current[i]
    n_tog, n_cp = groups_i[0], groups_i[1]
    tog_ptr = 2
    tog_idx = tog_ptr + n_tog + 1
    cp_ptr = tog_idx + groups_i[tog_ptr + n_tog]
    cp_idx = cp_ptr + n_cp + 1
    for g in range(n_tog):
        a, b = groups_i[tog_ptr + g], groups_i[tog_ptr + g + 1]
        total = out[groups_i[tog_idx + a]] / groups_f[a]  # summed in turn, as numpy's reduction up to 7 terms
        for k in range(a + 1, b):
            total += out[groups_i[tog_idx + k]] / groups_f[k]
        common = total / (b - a)
        for k in range(a, b):
            out[groups_i[tog_idx + k]] = groups_f[k] * common
    spreads = groups_i[tog_ptr + n_tog]  # the coupled groups' spreads follow the together gains
    for g in range(n_cp):
        a, b = groups_i[cp_ptr + g], groups_i[cp_ptr + g + 1]
        low = out[groups_i[cp_idx + a]]
        high = low
        for k in range(a + 1, b):
            v = out[groups_i[cp_idx + k]]
            low = min(low, v)
            high = max(high, v)
        spread = groups_f[spreads + g]
        if high - low > spread:
            mid = 0.5 * (low + high)
            for k in range(a, b):
                j = groups_i[cp_idx + k]
                out[j] = mid + (out[j] - mid) * (spread / (high - low))
    for i in range(n):
        v = out[i]
        if v < lo[i]:
            v = lo[i]
        if v > hi[i]:
            v = hi[i]
        out[i] = v


@njit(cache=True, fastmath=False)
def channel_targets(values: np.ndarray, x: np.ndarray, group_channel: np.ndarray, group_member: np.ndarray,
                    group_factor: np.ndarray, act_scale: np.ndarray) -> None:
    """The group and actuator channels of :func:`runtime.core.solve.to_targets` into ``x``: each finite group
    channel value times its factor onto each member (in the map's order: a later member entry wins), then each finite
    actuator channel value times its scale (channel k < len(act_scale) is actuator k); NaN channels leave ``x``."""
    for k in range(group_channel.shape[0]):
        v = values[group_channel[k]]
        if np.isfinite(v):
            x[group_member[k]] = v * group_factor[k]
    for k in range(act_scale.shape[0]):
        v = values[k]
        if np.isfinite(v):
            x[k] = v * act_scale[k]
