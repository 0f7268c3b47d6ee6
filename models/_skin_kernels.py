"""Compiled inner loops of the hidden-space inverse solve, the reduced strain measure and the guard's limit (numba).

Both run once per frame in the control loop. Written with numpy they are a few dozen small array operations each,
and on a two-core machine the interpreter's per-operation overhead (microseconds) is most of their cost; compiled,
the same arithmetic runs without it. The numpy versions stay in :mod:`models.ksnn_solve` and
:mod:`models.strain_guard` as the reference the tests compare against. Compiled on first use and cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from models._cycle_kernels import constrain
from models.kernel_args import (
    DAMPING_JUMP,
    REFRESH_STEP,
    pack_frame_args,  # noqa: F401 (the packing solve_values_measured unpacks)
)


@njit(cache=True, fastmath=False)
def _cholesky_solve(A: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """Solve A x = b (A symmetric positive definite, n small) into ``out``; False when A is not positive definite.
    ``A`` is overwritten by its Cholesky factor."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        A[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / d
    for i in range(n):  # L y = b
        s = b[i]
        for k in range(i):
            s -= A[i, k] * out[k]
        out[i] = s / A[i, i]
    for i in range(n - 1, -1, -1):  # Lᵀ x = y
        s = out[i]
        for k in range(i + 1, n):
            s -= A[k, i] * out[k]
        out[i] = s / A[i, i]
    return True


#: ln 2 split in two (its high part exact in few bits, so k·LN2_HI is exact for the k that occur) and 1 / ln 2.
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e+00


@njit(cache=True, fastmath={"contract"})
def _tanh_layer(W1: np.ndarray, x: np.ndarray, b1: np.ndarray, h: np.ndarray) -> None:
    """h = tanh(W1 x + b1), written into ``h``: tanh(v) = ±(1 − e)/(1 + e) with e = exp(−2|v|) = 2⁻ᵏ exp(r),
    k = round(2|v| / ln 2), |r| ≤ ln 2 / 2 (exp(r) by its Taylor series to r¹³, 4e-18 short), 2⁻ᵏ from its bits.
    Written as two plain loops the compiler vectorizes: a third of libm's per-element cost, which a frame pays for
    every hidden unit at every trial point; within 2.3e-16 of numpy's tanh (NaN stays NaN, ±inf gives ±1)."""
    n = h.shape[0]
    np.dot(W1, x, h)
    bits = np.empty(n, dtype=np.int64)
    scale = bits.view(np.float64)
    poly = np.empty(n)
    for i in range(n):
        a = min(2.0 * abs(h[i] + b1[i]), 700.0)  # exp(−700) ≈ 1e-304: tanh is ±1 long before
        k = np.floor(a * _INV_LN2 + 0.5)
        r = (k * _LN2_HI - a) + k * _LN2_LO  # −a + k ln 2
        poly[i] = 1.0 + r * (1.0 + r * (1 / 2 + r * (1 / 6 + r * (1 / 24 + r * (1 / 120 + r * (
            1 / 720 + r * (1 / 5040 + r * (1 / 40320 + r * (1 / 362880 + r * (1 / 3628800 + r * (
                1 / 39916800 + r * (1 / 479001600 + r * (1 / 6227020800)))))))))))))
        bits[i] = (1023 - np.int64(k)) << 52  # 2⁻ᵏ
    for i in range(n):
        e = poly[i] * scale[i]
        t = (1.0 - e) / (1.0 + e)
        h[i] = t if h[i] + b1[i] >= 0.0 else -t


@njit(cache=True)
def _hidden_at(W1: np.ndarray, x: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """tanh(W1 x + b1), a new array."""
    h = np.empty(W1.shape[0])
    _tanh_layer(W1, x, b1, h)
    return h


@njit(cache=True)
def _hidden_residual(x: np.ndarray, W1: np.ndarray, b1: np.ndarray, Rb: np.ndarray, q: np.ndarray,
                     h: np.ndarray, Rh: np.ndarray, r: np.ndarray) -> float:
    """h = tanh(W1 x + b1); Rh = R h (R block diagonal, blocks Rb: r × H per axis); r = Rh + q; returns r·r.
    Written into ``h``, ``Rh`` and ``r`` without temporaries: at these sizes allocating them costs as much as the
    arithmetic."""
    n = Rb.shape[1]
    H = Rb.shape[2]
    _tanh_layer(W1, x, b1, h)
    for k in range(3):
        np.dot(Rb[k], h[k * H:(k + 1) * H], Rh[k * n:(k + 1) * n])
    return _residual(Rh, q, r)


@njit(cache=True)
def _residual(Rh: np.ndarray, q: np.ndarray, r: np.ndarray) -> float:
    """r = Rh + q; returns r·r."""
    rr = 0.0
    for i in range(r.shape[0]):
        v = Rh[i] + q[i]
        r[i] = v
        rr += v * v
    return rr


@njit(cache=True)
def _gradient(Rb: np.ndarray, W1b: np.ndarray, h: np.ndarray, r: np.ndarray, t: np.ndarray, gk: np.ndarray,
              g: np.ndarray) -> None:
    """The exact gradient Jᵀr = W1ᵀ diag(1 − h²) Rᵀ r per axis block without forming J, into ``g`` (``t``, ``gk``:
    scratch of H and A)."""
    n = Rb.shape[1]
    H = Rb.shape[2]
    g[:] = 0.0
    for k in range(3):
        np.dot(r[k * n:(k + 1) * n], Rb[k], t)
        for i in range(H):
            t[i] *= 1.0 - h[k * H + i] ** 2
        np.dot(t, W1b[k], gk)
        for a in range(g.shape[0]):
            g[a] += gk[a]


@njit(cache=True)
def gauss_newton(x: np.ndarray, x_prev: np.ndarray, smooth: bool, lam_s: float, W1: np.ndarray, b1: np.ndarray,
                 W1b: np.ndarray, Rb: np.ndarray, Rm: np.ndarray, q: np.ndarray, kq: float, xlo: np.ndarray,
                 xhi: np.ndarray, mid: np.ndarray, ihalf: np.ndarray, mu: float, max_iterations: int, tol: float,
                 xtol: float, H0: np.ndarray, state: np.ndarray, h0: np.ndarray,
                 Rh0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, int, bool]:
    """The damped, projected Gauss-Newton of :meth:`models.ksnn_solve.KsnnInverse.solve`, step for step.

    ``Rm`` (3, m, H): the rows the Gauss-Newton matrix is formed from (``Rb`` itself: exact; fewer, the leading
    directions of :func:`models.ksnn_solve.leading_rows`, with the gradient then formed exactly without J).

    ``H0`` (A × A) and ``state`` (int64: age in frames of ``H0``, -1 none; the age up to which it is reused, 0 never;
    Gauss-Newton matrices formed) carry the reuse of the Gauss-Newton matrix JᵀJ across iterations and frames
    (:class:`models.ksnn_solve.HessianReuse`). ``h0``, ``Rh0``: the hidden activations at ``x`` and their product
    with R when known (the last frame's solution), else empty. Returns (x, h, R h, r, f, iterations, converged) in
    normalized units."""
    A = x.shape[0]
    n = Rb.shape[1]  # residual rows per axis: the output layer's rank (H when full)
    H = Rb.shape[2]
    h = np.empty(3 * H)
    Rh = np.empty(3 * n)
    r = np.empty(3 * n)
    h_new = np.empty(3 * H)
    Rh_new = np.empty(3 * n)
    r_new = np.empty(3 * n)
    x = x.copy()
    if h0.shape[0] > 0:
        h[:] = h0
        Rh[:] = Rh0
        f = _residual(Rh, q, r) + kq
    else:
        f = _hidden_residual(x, W1, b1, Rb, q, h, Rh, r) + kq
    if smooth:
        dx = x - x_prev
        f += lam_s * (dx @ dx)
    on_bound = np.max(np.abs(x - mid) * ihalf) >= 1.0 - 1e-12
    converged = False
    it = 0
    m = Rm.shape[1]  # rows per axis the matrix is formed from
    J = np.empty((3 * m, A))
    step = np.empty(A)
    fixed = np.zeros(A, dtype=np.bool_)
    reuse = state[1] > 0
    stored = reuse and 0 <= state[0] < state[1]  # this frame starts from the kept JᵀJ
    g = np.empty(A)
    gk = np.empty(A)
    t = np.empty(H)
    SW = np.empty((H, A))  # diag(1 − h²) W1 of one axis
    Hm = np.empty((A, A))  # this iteration's Gauss-Newton matrix
    M = np.empty((A, A))  # the damped matrix, factored in place
    x_new = np.empty(A)  # the trial point
    for it in range(1, max_iterations + 1):  # noqa: B007 - it is returned
        exact = not stored
        if exact:  # J = Rm diag(1 − h²) W1 per axis block: the O(m H A) part, into J without temporaries
            for k in range(3):
                for j in range(H):
                    sj = 1.0 - h[k * H + j] ** 2
                    for a in range(A):
                        SW[j, a] = W1b[k, j, a] * sj
                np.dot(Rm[k], SW, J[k * m:(k + 1) * m])
            if m == n:
                np.dot(r, J, g)
            else:
                _gradient(Rb, W1b, h, r, t, gk, g)
            np.dot(J.T, J, Hm)
            state[2] += 1
            if reuse:
                H0[:, :] = Hm
                state[0] = 0
                stored = True
        else:  # the kept JᵀJ
            _gradient(Rb, W1b, h, r, t, gk, g)
            Hm[:, :] = H0
        if smooth:
            g += lam_s * (x - x_prev)
        if on_bound:
            n_fixed = 0
            for a in range(A):
                fixed[a] = (x[a] <= xlo[a] and g[a] > 0.0) or (x[a] >= xhi[a] and g[a] < 0.0)
                n_fixed += fixed[a]
            if n_fixed == A:
                converged = True
                break
            if n_fixed > 0:
                for a in range(A):
                    if fixed[a]:
                        Hm[a, :] = 0.0
                        Hm[:, a] = 0.0
                        Hm[a, a] = 1.0
                        g[a] = 0.0
        trace = np.trace(Hm)
        base = (lam_s if smooth else 0.0) + 1e-14 * trace
        jump = DAMPING_JUMP * trace / A  # the least damping a retry uses
        accepted = False
        f_new = f
        u = 0.0
        for _ in range(8):
            M[:, :] = Hm
            for a in range(A):
                M[a, a] += base + mu
            if not _cholesky_solve(M, g, step):
                mu = max(mu * 10.0, 1e-12 * max(abs(f), 1e-30), jump)
                continue
            u = 0.0  # the trial point x − step, projected on the box when it leaves it
            for a in range(A):
                x_new[a] = x[a] - step[a]
                u = max(u, abs(x_new[a] - mid[a]) * ihalf[a])
            if u > 1.0:
                for a in range(A):
                    x_new[a] = min(max(x_new[a], xlo[a]), xhi[a])
            f_new = _hidden_residual(x_new, W1, b1, Rb, q, h_new, Rh_new, r_new) + kq
            if smooth:
                ss = 0.0
                for a in range(A):
                    ss += (x_new[a] - x_prev[a]) ** 2
                f_new += lam_s * ss
            if f_new <= f:
                accepted = True
                break
            mu = max(mu * 10.0, 1e-12 * max(abs(f), 1e-30), jump)
        if not accepted and not exact:  # the kept matrix gave no descent: form it afresh (the next iteration)
            stored = False
            continue
        if not accepted:
            converged = True  # no descent possible within damping limits: at a (local) minimum
            break
        mu *= 0.3
        decrease = f - f_new
        x, x_new = x_new, x
        f = f_new
        h, h_new = h_new, h
        Rh, Rh_new = Rh_new, Rh
        r, r_new = r_new, r
        on_bound = u >= 1.0 - 1e-12
        largest = 0.0
        for a in range(A):
            largest = max(largest, abs(step[a]))
        if xtol > 0.0 and largest <= xtol:
            converged = True
            break
        if decrease <= tol * max(f, 1e-30):
            if exact:
                converged = True
                break
            stored = False  # a kept matrix's small decrease is no proof of a minimum: check with a fresh one
        elif largest > REFRESH_STEP:
            stored = False  # a long step: the pose moved far from where the kept matrix was formed
    if reuse and state[0] >= 0:
        state[0] += 1
    return x, h, Rh, r, f, it, converged


@njit(cache=True)
def reduced_measure(h: np.ndarray, Q: np.ndarray, E: np.ndarray, e0: np.ndarray, tri: np.ndarray, C: np.ndarray,
                    idet: np.ndarray, S_ptr: np.ndarray, S_idx: np.ndarray, S_w: np.ndarray) -> tuple[float, float]:
    """The strain guard's reduced measure (min, max) from hidden activations (3H,): the computation of
    :meth:`models.strain_guard.StrainGuard.measure_hidden` (offsets and edge vectors in float32, as there). ``Q``
    (3, q, H): the basis the offsets' dependence on h lies in, offsets = (Q_k h_k) E_k with E (3, q, v) over the
    measured triangles' v vertices (:func:`models.strain_guard.edge_basis`); q = 0: none, offsets = h_k E_k with E
    (3, H, v). ``tri`` (3, n): each triangle's corners among those vertices; ``e0`` (3, 1, 2n): its two edges at
    h = 0."""
    H = Q.shape[2]
    nq = Q.shape[1]
    n = tri.shape[1]
    d = np.empty((3, E.shape[2]), dtype=np.float32)
    hk = np.empty(H, dtype=np.float32)
    zk = np.empty(nq, dtype=np.float32)
    for k in range(3):
        for i in range(H):
            hk[i] = h[k * H + i]
        if nq > 0:
            np.dot(Q[k], hk, zk)
            np.dot(zk, E[k], d[k])
        else:
            np.dot(hk, E[k], d[k])
    e = np.empty((3, 2 * n), dtype=np.float32)  # the edge vectors: differences of the corners' offsets, plus e0
    t0 = tri[0]
    t1 = tri[1]
    t2 = tri[2]
    for k in range(3):
        dk = d[k]
        ek = e[k]
        gk = e0[k, 0]
        for t in range(n):
            ek[t] = (dk[t1[t]] - dk[t0[t]]) + gk[t]
        for t in range(n):
            ek[n + t] = (dk[t2[t]] - dk[t0[t]]) + gk[n + t]
    lam_lo = np.empty(n)
    lam_hi = np.empty(n)
    for t in range(n):
        m00 = 0.0
        m01 = 0.0
        m11 = 0.0
        for k in range(3):
            a = np.float64(e[k, t])
            b = np.float64(e[k, n + t])
            m00 += a * a
            m01 += a * b
            m11 += b * b
        half_tr = m00 * C[0, 0, t] + m01 * (C[0, 1, t] + C[1, 0, t]) + m11 * C[1, 1, t]
        det = (m00 * m11 - m01 * m01) * idet[t]
        disc = np.sqrt(max(half_tr * half_tr - det, 0.0))
        lam_lo[t] = np.sqrt(max(half_tr - disc, 0.0))
        lam_hi[t] = np.sqrt(max(half_tr + disc, 0.0))
    # patch means (the dense patch matrix is 0.4 % full: by patch, sparse)
    lo_min = np.inf
    hi_max = -np.inf
    for q in range(S_ptr.shape[0] - 1):
        a = 0.0
        b = 0.0
        for k in range(S_ptr[q], S_ptr[q + 1]):
            a += lam_lo[S_idx[k]] * S_w[k]
            b += lam_hi[S_idx[k]] * S_w[k]
        lo_min = min(lo_min, a)
        hi_max = max(hi_max, b)
    return lo_min - 1.0, hi_max - 1.0


@njit(cache=True)
def _passes_measured(p: np.ndarray, scale: np.ndarray, shift: np.ndarray, W1: np.ndarray, b1: np.ndarray,
                     s_lo: float, s_hi: float, Q: np.ndarray, E: np.ndarray, e0: np.ndarray, tri: np.ndarray,
                     C: np.ndarray, idet: np.ndarray, S_ptr: np.ndarray, S_idx: np.ndarray,
                     S_w: np.ndarray) -> tuple[bool, float, float]:
    """:meth:`models.strain_guard.StrainGuard.check` and the reduced measure it read (NaN when ``p`` lies outside
    the trained range: normalized within 1e-6 of [0, 1]; NaN fails)."""
    x = p * scale + shift
    for v in x:
        if not (v >= -1e-6 and v <= 1.0 + 1e-6):
            return False, np.nan, np.nan
    lo, hi = reduced_measure(_hidden_at(W1, x, b1), Q, E, e0, tri, C, idet, S_ptr, S_idx, S_w)
    return s_lo <= lo and hi <= s_hi, lo, hi


@njit(cache=True)
def _passes(p: np.ndarray, scale: np.ndarray, shift: np.ndarray, W1: np.ndarray, b1: np.ndarray, s_lo: float,
            s_hi: float, Q: np.ndarray, E: np.ndarray, e0: np.ndarray, tri: np.ndarray, C: np.ndarray, idet: np.ndarray,
            S_ptr: np.ndarray, S_idx: np.ndarray, S_w: np.ndarray) -> bool:
    """:meth:`models.strain_guard.StrainGuard.check`: ``p`` inside the trained range (normalized within 1e-6 of [0,
    1]; NaN fails) and its reduced measure within [s_lo, s_hi]."""
    return _passes_measured(p, scale, shift, W1, b1, s_lo, s_hi, Q, E, e0, tri, C, idet, S_ptr, S_idx, S_w)[0]


@njit(cache=True)
def _limit_from(p_from: np.ndarray, p_to: np.ndarray, steps: int, out: np.ndarray, scale: np.ndarray,
                shift: np.ndarray, W1: np.ndarray, b1: np.ndarray, s_lo: float, s_hi: float, Q: np.ndarray,
                E: np.ndarray, e0: np.ndarray, tri: np.ndarray, C: np.ndarray, idet: np.ndarray, S_ptr: np.ndarray,
                S_idx: np.ndarray, S_w: np.ndarray, measure_held: bool) -> tuple[int, float, float]:
    """:func:`guard_limit` once ``p_to`` is known to fail: ``out`` the furthest passing point of the segment from
    ``p_from`` found by ``steps`` bisections (1), else ``p_from`` (2); with the reduced measure of ``out`` as
    :meth:`models.strain_guard.StrainGuard.measure` gives it (at the pose clamped to the trained range; for
    ``p_from`` only with ``measure_held``, else NaN)."""
    d = p_to - p_from
    lo_t, hi_t, found = 0.0, 1.0, False
    m_lo, m_hi = 0.0, 0.0
    for _ in range(steps):
        mid = 0.5 * (lo_t + hi_t)
        ok, a, b = _passes_measured(p_from + mid * d, scale, shift, W1, b1, s_lo, s_hi, Q, E, e0, tri, C, idet, S_ptr,
                                    S_idx, S_w)
        if ok:
            lo_t, found, m_lo, m_hi = mid, True, a, b
        else:
            hi_t = mid
    if found:
        out[:] = p_from + lo_t * d
        return 1, m_lo, m_hi
    out[:] = p_from
    if not measure_held:
        return 2, np.nan, np.nan
    x = np.minimum(np.maximum(p_from * scale + shift, 0.0), 1.0)
    m_lo, m_hi = reduced_measure(_hidden_at(W1, x, b1), Q, E, e0, tri, C, idet, S_ptr, S_idx, S_w)
    return 2, m_lo, m_hi


@njit(cache=True)
def guard_limit(p_from: np.ndarray, p_to: np.ndarray, steps: int, out: np.ndarray, scale: np.ndarray,
                shift: np.ndarray, W1: np.ndarray, b1: np.ndarray, s_lo: float, s_hi: float, Q: np.ndarray,
                E: np.ndarray, e0: np.ndarray, tri: np.ndarray, C: np.ndarray, idet: np.ndarray, S_ptr: np.ndarray,
                S_idx: np.ndarray, S_w: np.ndarray) -> int:
    """:meth:`models.strain_guard.StrainGuard.limit` in one call: ``out`` = ``p_to`` when it passes (returns 0), else
    the furthest passing point of the segment from ``p_from`` found by ``steps`` bisections (1), else ``p_from`` (2)."""
    if _passes(p_to, scale, shift, W1, b1, s_lo, s_hi, Q, E, e0, tri, C, idet, S_ptr, S_idx, S_w):
        out[:] = p_to
        return 0
    return _limit_from(p_from, p_to, steps, out, scale, shift, W1, b1, s_lo, s_hi, Q, E, e0, tri, C, idet, S_ptr, S_idx,
                       S_w, False)[0]


@njit(cache=True)
def guard_step(targets: np.ndarray, current: np.ndarray, p_from: np.ndarray, steps: int, out: np.ndarray,
               lo: np.ndarray, hi: np.ndarray, groups_i: np.ndarray, groups_f: np.ndarray, scale: np.ndarray,
               shift: np.ndarray, W1: np.ndarray, b1: np.ndarray, s_lo: float, s_hi: float, Q: np.ndarray,
               E: np.ndarray, e0: np.ndarray, tri: np.ndarray, C: np.ndarray, idet: np.ndarray, S_ptr: np.ndarray,
               S_idx: np.ndarray, S_w: np.ndarray) -> int:
    """The control cycle's guard stage in one call: ``targets`` constrained to the head's limits and groups
    (:func:`models._cycle_kernels.constrain`, holds from ``current``), then, unless that is ``p_from`` itself
    (returns -1, ``out`` the constrained target), :func:`guard_limit` from ``p_from`` (its verdict code)."""
    x = np.empty_like(targets)
    constrain(targets, current, lo, hi, groups_i, groups_f, x)
    same = True
    for i in range(x.shape[0]):
        if x[i] != p_from[i]:
            same = False
            break
    if same:
        out[:] = x
        return -1
    return guard_limit(p_from, x, steps, out, scale, shift, W1, b1, s_lo, s_hi, Q, E, e0, tri, C, idet, S_ptr, S_idx,
                       S_w)


@njit(cache=True)
def _terms(wts: np.ndarray, const_b: float, e: np.ndarray, M: np.ndarray, q0: np.ndarray,
           QdT: np.ndarray) -> tuple[np.ndarray, float]:
    """The residual's offset q = q0 − Qd w and the constant κ = b − 2 w·e + wᵀMw from the face-unit weights that are
    not zero only (``QdT`` = Qdᵀ, by unit): a frame sets few of its channels, and reading only their rows of Qdᵀ
    and M leaves most of those constants out of the memory a frame reads."""
    U = wts.shape[0]
    nz = np.empty(U, dtype=np.int64)
    c = 0
    for u in range(U):
        if wts[u] != 0.0:
            nz[c] = u
            c += 1
    q = q0.copy()
    kappa = const_b
    for a in range(c):
        i = nz[a]
        wi = wts[i]
        s = 0.0
        for b in range(c):
            s += M[i, nz[b]] * wts[nz[b]]
        kappa += wi * (s - 2.0 * e[i])
        row = QdT[i]
        for j in range(q.shape[0]):
            q[j] -= wi * row[j]
    return q, kappa


@njit(cache=True)
def solve_frame(wts: np.ndarray, p_prev: np.ndarray, p0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                scale_in: np.ndarray, const_b: float, e: np.ndarray, M: np.ndarray, q0: np.ndarray, QdT: np.ndarray,
                lam_s: float, W1: np.ndarray, b1: np.ndarray, W1b: np.ndarray, Rb: np.ndarray, Rm: np.ndarray,
                xlo: np.ndarray, xhi: np.ndarray, mid: np.ndarray, ihalf: np.ndarray, mu: float, max_iterations: int,
                tol: float, xtol: float, H0: np.ndarray, state: np.ndarray,
                carry: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float, int, bool]:
    """One frame of :meth:`models.ksnn_solve.KsnnInverse.solve` from face-unit weights to actuator values: the
    objective's terms, the start (``p0``, else ``p_prev``, else mid-range; empty arrays mean absent), the
    iteration. Returns (p, hidden, unscaled squared error, objective, iterations, converged).

    ``carry`` (:attr:`models.ksnn_solve.HessianReuse.carry`; empty: none) keeps the solution for the next frame:
    [kept (1.0) or not, p (A), its normalized x (A), h (3H), R h (3r)]. A frame warm-started from exactly that p
    starts from that x with its h and R h instead of computing them again (the first residual, a tenth of a
    frame); each frame writes its own. ``QdT`` (U, 3r): the residual's offset per face-unit weight, by unit."""
    q, kappa = _terms(wts, const_b, e, M, q0, QdT)
    A = lo.shape[0]
    H3 = W1.shape[0]
    N3 = Rb.shape[0] * Rb.shape[1]
    has_prev = p_prev.shape[0] > 0
    x_prev = (p_prev - lo) * scale_in if has_prev else np.empty(0)
    kept = carry.shape[0] > 0 and carry[0] == 1.0 and has_prev and p0.shape[0] == 0
    if kept:
        for i in range(A):
            if carry[1 + i] != p_prev[i]:
                kept = False
                break
    h0 = carry[1 + 2 * A:1 + 2 * A + H3] if kept else carry[0:0]
    Rh0 = carry[1 + 2 * A + H3:1 + 2 * A + H3 + N3] if kept else carry[0:0]
    if kept:
        x = carry[1 + A:1 + 2 * A].copy()
    elif p0.shape[0] > 0:
        x = np.minimum(np.maximum((p0 - lo) * scale_in, xlo), xhi)
    elif has_prev:
        x = np.minimum(np.maximum(x_prev, xlo), xhi)
    else:
        x = np.minimum(np.maximum(np.full(A, 0.5), xlo), xhi)
    smooth = has_prev and lam_s > 0.0
    kq = kappa - q @ q
    x, h, Rh, r, f, it, converged = gauss_newton(x, x_prev, smooth, lam_s, W1, b1, W1b, Rb, Rm, q, kq, xlo, xhi,
                                                 mid, ihalf, mu, max_iterations, tol, xtol, H0, state, h0, Rh0)
    p = lo + x * (hi - lo)
    if carry.shape[0] > 0:
        carry[1:1 + A] = p
        carry[1 + A:1 + 2 * A] = x
        carry[1 + 2 * A:1 + 2 * A + H3] = h
        carry[1 + 2 * A + H3:1 + 2 * A + H3 + N3] = Rh
        carry[0] = 1.0
    return p, h, max(r @ r + kq, 0.0), f, it, converged


@njit(cache=True)
def solve_frame_measured(wts: np.ndarray, p_prev: np.ndarray, p0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                         scale_in: np.ndarray, const_b: float, e: np.ndarray, M: np.ndarray, q0: np.ndarray,
                         QdT: np.ndarray, lam_s: float, W1: np.ndarray, b1: np.ndarray, W1b: np.ndarray, Rb: np.ndarray,
                         Rm: np.ndarray, xlo: np.ndarray, xhi: np.ndarray, mid: np.ndarray, ihalf: np.ndarray,
                         mu: float, max_iterations: int, tol: float, xtol: float, H0: np.ndarray, state: np.ndarray,
                         carry: np.ndarray, Q: np.ndarray, E: np.ndarray, ge0: np.ndarray, tri: np.ndarray,
                         C: np.ndarray, idet: np.ndarray, S_ptr: np.ndarray, S_idx: np.ndarray, S_w: np.ndarray):
    """:func:`solve_frame` and the strain guard's :func:`reduced_measure` of its solution in one call (a frame's
    whole in-cycle work, one dispatch); returns solve_frame's tuple plus (strain min, strain max)."""
    p, h, fit, f, it, conv = solve_frame(wts, p_prev, p0, lo, hi, scale_in, const_b, e, M, q0, QdT, lam_s, W1, b1,
                                         W1b, Rb, Rm, xlo, xhi, mid, ihalf, mu, max_iterations, tol, xtol, H0, state,
                                         carry)
    s_lo, s_hi = reduced_measure(h, Q, E, ge0, tri, C, idet, S_ptr, S_idx, S_w)
    return p, h, fit, f, it, conv, s_lo, s_hi


@njit(cache=True)
def solve_values_measured(values: np.ndarray, wts: np.ndarray, p_prev: np.ndarray, p_out: np.ndarray,
                          H0: np.ndarray, state: np.ndarray, carry: np.ndarray, f64: np.ndarray, f32: np.ndarray,
                          i64: np.ndarray, dims: np.ndarray) -> tuple[float, int, float, float, int]:
    """A control frame from channel values: the face-unit weights (a value clamped to 0..1, a non-finite one, i.e.
    not set, as 0) written into ``wts``, then :func:`solve_frame_measured` warm-started from ``p_prev`` on the
    constants :func:`pack_frame_args` packed; ``H0``, ``state`` and ``carry``: what the frame solve keeps from
    frame to frame (:func:`gauss_newton`, :func:`solve_frame`). When the solution's measure leaves the strain range,
    the guard's search (:func:`guard_limit`) from ``p_prev`` toward it, with the packed number of bisections (none
    packed: no guard). The pose is written into ``p_out`` (no array crosses back into Python). Returns (unscaled
    squared error of the solution, iterations, strain min, strain max of the pose written, verdict: 0 the solution
    passed, 1 limited, 2 held at ``p_prev``, -1 not guarded)."""
    for i in range(wts.shape[0]):
        v = values[i]
        wts[i] = min(max(v, 0.0), 1.0) if np.isfinite(v) else 0.0
    A, U, H, T, P1, NZ, E2, max_iterations = dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7]
    n = dims[9]  # residual rows per axis (the output layer's rank)
    H3 = 3 * H
    N3 = 3 * n
    lo = f64[0:A]
    hi = f64[A:2 * A]
    scale_in = f64[2 * A:3 * A]
    xlo = f64[3 * A:4 * A]
    xhi = f64[4 * A:5 * A]
    mid = f64[5 * A:6 * A]
    ihalf = f64[6 * A:7 * A]
    o = 7 * A
    e = f64[o:o + U]
    o += U
    M = f64[o:o + U * U].reshape(U, U)
    o += U * U
    q0 = f64[o:o + N3]
    o += N3
    QdT = f64[o:o + U * N3].reshape(U, N3)
    o += N3 * U
    W1 = f64[o:o + H3 * A].reshape(H3, A)
    o += H3 * A
    b1 = f64[o:o + H3]
    o += H3
    W1b = W1.reshape(3, H, A)  # the same numbers by axis block (packed once)
    Rb = f64[o:o + N3 * H].reshape(3, n, H)
    o += N3 * H
    m = dims[10]  # rows per axis the Gauss-Newton matrix is formed from
    Rm = f64[o:o + 3 * m * H].reshape(3, m, H)
    o += 3 * m * H
    C = f64[o:o + 4 * T].reshape(2, 2, T)
    o += 4 * T
    idet = f64[o:o + T]
    o += T
    S_w = f64[o:o + NZ]
    o += NZ
    const_b, lam_s, mu, tol, xtol = f64[o], f64[o + 1], f64[o + 2], f64[o + 3], f64[o + 4]
    o += 5
    g_scale = f64[o:o + A]
    g_shift = f64[o + A:o + 2 * A]
    lim_lo, lim_hi = f64[o + 2 * A], f64[o + 2 * A + 1]
    steps = dims[8]
    nq = dims[11]  # rows of the guard's edge basis (0: none)
    Q = f32[0:3 * nq * H].reshape(3, nq, H)
    o32 = 3 * nq * H
    ER = nq if nq > 0 else H  # rows of E
    E = f32[o32:o32 + 3 * ER * E2].reshape(3, ER, E2)
    o32 += 3 * ER * E2
    ge0 = f32[o32:o32 + 6 * T].reshape(3, 1, 2 * T)
    S_ptr = i64[0:P1]
    S_idx = i64[P1:P1 + NZ]
    tri = i64[P1 + NZ:P1 + NZ + 3 * T].reshape(3, T)
    p, _, fit, _, it, _, s_lo, s_hi = solve_frame_measured(
        wts, p_prev, np.empty(0), lo, hi, scale_in, const_b, e, M, q0, QdT, lam_s, W1, b1, W1b, Rb, Rm, xlo, xhi, mid,
        ihalf, mu, max_iterations, tol, xtol, H0, state, carry, Q, E, ge0, tri, C, idet, S_ptr, S_idx, S_w)
    if steps < 0:
        p_out[:] = p
        return fit, it, s_lo, s_hi, -1
    if lim_lo <= s_lo and s_hi <= lim_hi:  # the solution lies in the trained range by construction
        p_out[:] = p
        return fit, it, s_lo, s_hi, 0
    verdict, s_lo, s_hi = _limit_from(p_prev, p, steps, p_out, g_scale, g_shift, W1, b1, lim_lo, lim_hi, Q, E, ge0,
                                      tri, C, idet, S_ptr, S_idx, S_w, True)
    return fit, it, s_lo, s_hi, verdict
