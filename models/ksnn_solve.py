"""Inverse skin solve in the KSNN hidden space: actuator values whose predicted surface matches a target.

For each axis k the KSNN predicts offsets y_k = W2_kᵀ h_k + b2_k with h_k = tanh(W1_kᵀ p̂ + b1_k). The target
surface is base + Σ wᵢ Δᵢ (face-unit offsets Δᵢ), so with vertex weights S the surface residual

    ‖S (y − Σ wᵢ Δᵢ)‖² = Σ_k h_kᵀ G_k h_k + 2 h_kᵀ (c_k − D_k w) + const(w),
    G_k = W2_k S² W2_kᵀ (H×H),  c_k = W2_k S² b2_k,  D_k = W2_k S² Δ_kᵀ (H×U),

is exact in the H-dimensional hidden space. Factoring G_k = R_kᵀ R_k (eigen-decomposition) turns it into the least-
squares residual ρ = R h + q(w) of size 3r (r ≤ H the rank of the output layer W2_k), so each damped Gauss-Newton
step costs O(r H A + r U) and does not depend on the vertex count. Inputs are solved in normalized units p̂ ∈ [0, 1]
with box limits (projected, with an active set), a temporal smoothness term towards the previous frame, and a warm
start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from models.kernel_args import DAMPING_JUMP, REFRESH_STEP
from models.kernel_support import kernels_available
from models.predictor import KsnnWeights
from models.strain_guard import VERDICTS

if TYPE_CHECKING:
    from models.strain_guard import StrainGuard

_EMPTY = np.empty(0)
#: Frames a control frame solve keeps its Gauss-Newton matrix (:class:`HessianReuse`): 16 at 500 Hz is 32 ms.
REUSE_FRAMES = 16


@dataclass(frozen=True)
class SolveResult:
    """One inverse solve: actuator values (raw SI units), RMS surface residual (m), iterations, convergence."""

    p: np.ndarray
    residual_rms: float
    iterations: int
    converged: bool
    objective: float
    hidden: np.ndarray | None = None  # hidden activations (3H,) at p, for the strain guard
    strain: tuple[float, float] | None = None  # the guard's reduced measure at p, when solve() was given the guard


class KsnnInverse:
    """Precomputed hidden-space inverse of one KSNN for one set of face units and vertex weights.

    ``face_units`` (U, V, 3) are target offsets per unit weight; ``vertex_weights`` (V,) select/weight surface
    vertices (default 1). ``smoothness`` weighs ‖p̂ − p̂_prev‖² against the mean squared vertex error (m²):
    the default makes a full-range jump of one actuator cost as much as 0.3 mm RMS surface error. ``compiled``
    runs the iteration compiled (the same steps; numpy's interpreter overhead is most of a frame's cost otherwise);
    default: compiled when numba is installed. ``matrix_rank`` (default: the output rank, exact Gauss-Newton) forms
    the Gauss-Newton matrix from that many leading directions per axis of the residual's Jacobian over the pose box
    (:func:`leading_rows`); the gradient and the objective stay exact, so the minimizer is the same and only the
    steps' model is cheaper (J costs O(m H A) instead of O(r H A)).
    """

    def __init__(self, weights: KsnnWeights, face_units: np.ndarray, vertex_weights: np.ndarray | None = None,
                 smoothness: float = (0.3e-3) ** 2, damping: float = 1e-12, lo: np.ndarray | None = None,
                 hi: np.ndarray | None = None, compiled: bool | None = None, matrix_rank: int | None = None) -> None:
        w = weights
        n_vert = w.n_vertices
        fu = np.asarray(face_units, dtype=np.float64)
        if fu.ndim != 3 or fu.shape[1:] != (n_vert, 3):
            raise ValueError(f"face_units must have shape (U, {n_vert}, 3), got {fu.shape}")
        s2 = np.ones(n_vert) if vertex_weights is None else np.asarray(vertex_weights, dtype=np.float64) ** 2
        if s2.shape != (n_vert,) or not np.all(np.isfinite(s2)) or s2.sum() <= 0:
            raise ValueError(f"vertex_weights must be ({n_vert},) finite with a positive sum")
        self.weights = w
        # the compiled iteration (models._skin_kernels) where numba is installed; else the numpy reference
        self.compiled = kernels_available() if compiled is None else bool(compiled)
        self.n_units = fu.shape[0]
        self.smoothness = float(smoothness)
        self.damping = float(damping)
        self.scale = 1.0 / s2.sum()  # objective = mean squared weighted vertex error
        self.lo = w.lo if lo is None else np.asarray(lo, dtype=np.float64)
        self.hi = w.hi if hi is None else np.asarray(hi, dtype=np.float64)
        # Normalized-space box for the solve (a head may narrow the trained range).
        self._xlo = w.normalize(self.lo)
        self._xhi = w.normalize(self.hi)
        H = w.hidden
        A = w.n_actuators
        # G_k's eigen-decomposition; only its nonzero part enters the residual, so an output layer of rank r < H
        # (a wide hidden layer feeding fewer output directions) gives a residual of 3r and J of O(r H A) per step.
        eig = []
        for k in range(3):
            W2s = w.W2[k] * s2[None, :]  # (H, V)
            lam, Q = np.linalg.eigh(W2s @ w.W2[k].T)
            keep = lam > lam.max() * 1e-10  # singular values of W2 S under 1e-5 of the largest: float32 noise
            eig.append((W2s, lam[keep], Q[:, keep]))
        r = max(len(lam) for _, lam, _ in eig)  # rows per axis block (an axis of lower rank: zero rows first)
        R = np.zeros((3 * r, 3 * H))
        P = np.zeros((3 * r, 3 * H))
        q0 = np.zeros(3 * r)
        Qd = np.zeros((3 * r, self.n_units))
        const_b = 0.0
        e = np.zeros(self.n_units)
        M = np.zeros((self.n_units, self.n_units))
        for k, (W2s, lam, Q) in enumerate(eig):
            rows = slice((k + 1) * r - len(lam), (k + 1) * r)
            cols = slice(k * H, (k + 1) * H)
            c = W2s @ w.b2[k]
            D = W2s @ fu[:, :, k].T  # (H, U)
            sq = np.sqrt(lam)
            Pk = (Q / sq).T  # maps c − D w to q
            R[rows, cols] = (Q * sq).T  # R_kᵀ R_k = G_k
            P[rows, cols] = Pk
            q0[rows] = Pk @ c
            Qd[rows] = Pk @ D
            const_b += float(w.b2[k] @ (s2 * w.b2[k]))
            fs = fu[:, :, k] * s2[None, :]
            e += fs @ w.b2[k]
            M += fs @ fu[:, :, k].T
        self.rank = r
        G = R.T @ R  # block-diagonal PSD Gram of the hidden layer (3H × 3H)
        self._G = np.ascontiguousarray(G)
        self._Gb = np.ascontiguousarray(np.stack([G[k * H:(k + 1) * H, k * H:(k + 1) * H] for k in range(3)]))
        self._c0 = R.T @ q0  # linear term: c(w) = c0 − Cd w
        self._R = np.ascontiguousarray(R)
        self._Rb = np.ascontiguousarray(np.stack([R[k * r:(k + 1) * r, k * H:(k + 1) * H] for k in range(3)]))
        self._q0 = q0
        self._Qd = np.ascontiguousarray(Qd)
        self._QdT = np.ascontiguousarray(Qd.T)  # by face unit, as the compiled frame reads it
        self._Cd = np.ascontiguousarray(R.T @ Qd)
        self._const_b = const_b
        self._e = e
        self._M = M
        self._W1 = np.ascontiguousarray(np.concatenate([w.W1[k].T for k in range(3)], axis=0))  # (3H, A)
        self._b1 = np.concatenate(list(w.b1))
        self._W1b = np.ascontiguousarray(self._W1.reshape(3, H, A))
        self._H = H
        self._eye = np.eye(A)
        self._scale_in = 1.0 / (w.hi - w.lo)
        self._mid = 0.5 * (self._xlo + self._xhi)
        half = 0.5 * (self._xhi - self._xlo)
        self._ihalf = np.where(half > 0, 1.0 / np.where(half > 0, half, 1.0), 1e300)
        if matrix_rank is not None and (isinstance(matrix_rank, bool) or not isinstance(matrix_rank, int | np.integer)
                                        or matrix_rank < 1):
            raise ValueError(f"matrix_rank must be a positive integer, got {matrix_rank!r}")
        if matrix_rank is None or matrix_rank >= r:
            self.matrix_rank = r
            self._Rm = self._Rb  # exact: the matrix from the residual's own rows
        else:
            self.matrix_rank = int(matrix_rank)
            self._Rm = leading_rows(self._Rb, self._W1b, self._b1, self._xlo, self._xhi, self.matrix_rank)
        if self.compiled:  # compile (or load the cached kernel) now, never in a control cycle
            self.solve(np.zeros(self.n_units), max_iterations=1)

    # ------------------------------------------------------------------ pieces
    def kernel_arrays(self, exact_matrix: bool = False) -> tuple[np.ndarray | float, ...]:
        """The constants the compiled frame solve (:mod:`models._skin_kernels`) takes after the weights and the
        starts: raw limits, input scale, the objective's terms, the network, the rows the Gauss-Newton matrix is
        formed from (the residual's own with ``exact_matrix``), the box, smoothness and damping."""
        w = self.weights
        Rm = self._Rb if exact_matrix else self._Rm
        return (w.lo, w.hi, self._scale_in, self._const_b, self._e, self._M, self._q0, self._QdT,
                self.smoothness / self.scale, self._W1, self._b1, self._W1b, self._Rb, Rm, self._xlo, self._xhi,
                self._mid, self._ihalf, self.damping / self.scale)

    @property
    def carry_size(self) -> int:
        """Length of the carry a frame solve keeps for the next (:attr:`HessianReuse.carry`): a flag, the
        solution's pose and normalized pose, its hidden activations and their product with R."""
        A = len(self.lo)
        return 1 + 2 * A + 3 * self._H + 3 * self.rank

    def frame_state(self, frames: int = REUSE_FRAMES) -> HessianReuse:
        """What a frame solve of this inverse keeps from frame to frame: the Gauss-Newton matrix, used up to
        ``frames`` frames old, and the last solution's hidden activations (:class:`HessianReuse`)."""
        return HessianReuse(len(self.lo), frames, self.carry_size)

    def _checked(self, reuse: HessianReuse) -> HessianReuse:
        """``reuse``, refused when its carry belongs to another inverse's sizes."""
        if len(reuse.carry) not in (0, self.carry_size) or reuse.matrix.shape != (len(self.lo), len(self.lo)):
            raise ValueError(f"reuse: a frame state of {len(reuse.carry)} carried values and a "
                             f"{reuse.matrix.shape} matrix does not fit this inverse ({self.carry_size}, "
                             f"{len(self.lo)} actuators); make it with KsnnInverse.frame_state")
        return reuse

    def frame_solve(self, max_iterations: int, tol: float, xtol: float, measure: StrainGuard,
                    reuse_frames: int = REUSE_FRAMES, guard_steps: int | None = None) -> FrameSolve:
        """The in-cycle solve with these settings and ``measure`` bound (see :class:`FrameSolve`)."""
        return FrameSolve(self, max_iterations, tol, xtol, measure, reuse_frames, guard_steps)

    def _terms(self, wts: np.ndarray) -> tuple[np.ndarray, float]:
        """Linear term c and constant κ of f(h) = hᵀGh + 2hᵀc + κ (the unscaled squared surface error)."""
        c = self._c0 - self._Cd @ wts
        kappa = self._const_b - 2.0 * float(wts @ self._e) + float(wts @ (self._M @ wts))
        return c, kappa

    def hidden(self, x: np.ndarray) -> np.ndarray:
        """Hidden activations (3H,) at normalized pose x."""
        return np.tanh(self._W1 @ x + self._b1)

    def surface_error(self, p: np.ndarray, unit_weights: np.ndarray) -> float:
        """Exact mean squared weighted vertex error (m²) of the prediction at raw pose p vs the target."""
        c, kappa = self._terms(np.asarray(unit_weights, dtype=np.float64))
        h = self.hidden(self.weights.normalize(p))
        return max(float(h @ (self._G @ h + 2.0 * c)) + kappa, 0.0) * self.scale

    def solve(self, unit_weights: np.ndarray, p_prev: np.ndarray | None = None, p0: np.ndarray | None = None,
              max_iterations: int = 20, tol: float = 1e-9, xtol: float = 0.0,
              measure: StrainGuard | None = None, reuse: HessianReuse | None = None) -> SolveResult:
        """Damped, projected Gauss-Newton from ``p0`` (default ``p_prev``, else mid-range) for face-unit weights.

        ``tol`` bounds the relative decrease of the objective that counts as converged; ``xtol`` (normalized
        units, 0 = off) the largest actuator step that does (a warm-started frame whose first step is that small
        is done). Each iteration costs a
        few dozen small array operations (O(r H A) flops) and one 13×13-sized Cholesky solve (LAPACK ``dposv``);
        variables at a bound whose gradient pushes outward are held (their rows become identity). ``measure``, a
        :class:`models.strain_guard.StrainGuard` on the same predictor, adds its reduced strain measure at the
        solution (``SolveResult.strain``), computed in the same compiled call when both are compiled. ``reuse`` keeps
        the Gauss-Newton matrix between iterations and calls (:class:`HessianReuse`); without it every iteration
        forms its own. With a carry (:meth:`frame_state`) a solve warm-started from exactly the pose the last one
        returned starts from that solution's normalized pose and hidden activations.
        """
        wts = np.asarray(unit_weights, dtype=np.float64)
        if wts.shape != (self.n_units,) or not np.isfinite(wts @ wts):
            raise ValueError(f"unit_weights must be {self.n_units} finite numbers, got shape {wts.shape}")
        if self.compiled:
            from models.kernels_aot import kernel

            none = _EMPTY
            kept = HessianReuse(len(self.lo), 0) if reuse is None else self._checked(reuse)
            args = (wts, none if p_prev is None else np.asarray(p_prev, dtype=np.float64),
                    none if p0 is None else np.asarray(p0, dtype=np.float64), *self.kernel_arrays(),
                    max_iterations, tol, xtol, kept.matrix, kept.state, kept.carry)
            strain = None
            if measure is not None and measure.compiled:
                p, h, fit, f, it, conv, s_lo, s_hi = kernel("solve_frame_measured")(*args, *measure.kernel_arrays())
                strain = (float(s_lo), float(s_hi))
            else:
                p, h, fit, f, it, conv = kernel("solve_frame")(*args)
                if measure is not None:
                    strain = measure.measure_hidden(h)
            return SolveResult(p=p, residual_rms=float(np.sqrt(fit * self.scale)), iterations=it, converged=conv,
                               objective=f * self.scale, hidden=h, strain=strain)
        kappa = self._const_b - 2.0 * float(wts @ self._e) + float(wts @ (self._M @ wts))
        w = self.weights
        xlo, xhi = self._xlo, self._xhi
        W1, b1, H = self._W1, self._b1, self._H
        A = w.n_actuators
        x_prev = None if p_prev is None else (np.asarray(p_prev, dtype=np.float64) - w.lo) * self._scale_in
        carry = _EMPTY if reuse is None else self._checked(reuse).carry
        H3, N3 = 3 * H, 3 * self.rank
        kept = (len(carry) > 0 and carry[0] == 1.0 and p0 is None and p_prev is not None
                and np.array_equal(carry[1:1 + A], p_prev))
        if kept:  # the last solution, as the compiled solve_frame keeps it
            x = carry[1 + A:1 + 2 * A].copy()
        elif p0 is None and x_prev is not None:
            x = np.minimum(np.maximum(x_prev, xlo), xhi)
        elif p0 is not None:
            x = np.minimum(np.maximum((np.asarray(p0, dtype=np.float64) - w.lo) * self._scale_in, xlo), xhi)
        else:
            x = np.minimum(np.maximum(np.full(A, 0.5), xlo), xhi)
        lam_s = self.smoothness / self.scale  # in the unscaled objective
        smooth = x_prev is not None and lam_s > 0.0
        # Residual form: f = ‖R h + q‖² + κ' (+ λ‖x − x_prev‖²); J = R diag(1 − h²) W1 per axis block.
        q = self._q0 - self._Qd @ wts
        kq = kappa - float(q @ q)
        R, Rb, Rm, W1b, eye = self._R, self._Rb, self._Rm, self._W1b, self._eye
        mid, ihalf = self._mid, self._ihalf
        if kept:
            h = carry[1 + 2 * A:1 + 2 * A + H3].copy()
            Rh = carry[1 + 2 * A + H3:1 + 2 * A + H3 + N3].copy()
        else:
            h = np.tanh(W1 @ x + b1)
            Rh = R @ h
        r = Rh + q
        f = float(r @ r) + kq
        if smooth:
            dx = x - x_prev
            f += lam_s * float(dx @ dx)
        mu = self.damping / self.scale
        on_bound = float((np.abs(x - mid) * ihalf).max()) >= 1.0 - 1e-12
        converged = False
        it = 0
        state = None if reuse is None or reuse.frames <= 0 else reuse.state
        stored = state is not None and 0 <= state[0] < state[1]
        for it in range(1, max_iterations + 1):  # noqa: B007 - it is reported
            exact = not stored
            if exact:
                J = np.matmul(Rm * (1.0 - h * h).reshape(3, 1, H), W1b).reshape(-1, A)
                JT = J.T
                g = JT @ r if Rm is Rb else _gradient(Rb, W1b, h, r)
                Hm = JT @ J
                if reuse is not None:
                    reuse.state[2] += 1
                if state is not None:
                    reuse.matrix[:] = Hm
                    state[0] = 0
                    stored = True
            else:  # the exact gradient without forming J, the kept matrix
                g = _gradient(Rb, W1b, h, r)
                Hm = reuse.matrix.copy()
            if smooth:
                g += lam_s * dx
            if on_bound:
                fixed = ((x <= xlo) & (g > 0)) | ((x >= xhi) & (g < 0))
                if fixed.all():
                    converged = True
                    break
                if fixed.any():  # held variables: identity rows, zero gradient
                    Hm[fixed, :] = 0.0
                    Hm[:, fixed] = 0.0
                    Hm[fixed, fixed] = 1.0
                    g[fixed] = 0.0
            trace = float(Hm.trace())
            base = (lam_s if smooth else 0.0) + 1e-14 * trace
            jump = DAMPING_JUMP * trace / A  # the least damping a retry uses
            accepted = False
            for _ in range(8):
                _, step, info = _dposv()(Hm + (base + mu) * eye, g)
                if info != 0:
                    mu = max(mu * 10.0, 1e-12 * max(abs(f), 1e-30), jump)
                    continue
                y = x - step
                u = float((np.abs(y - mid) * ihalf).max())  # ≥ 1: some variable at or beyond a bound
                x_new = np.minimum(np.maximum(y, xlo), xhi) if u > 1.0 else y
                h_new = np.tanh(W1 @ x_new + b1)
                Rh_new = R @ h_new
                r_new = Rh_new + q
                f_new = float(r_new @ r_new) + kq
                if smooth:
                    dx_new = x_new - x_prev
                    f_new += lam_s * float(dx_new @ dx_new)
                if f_new <= f:
                    accepted = True
                    break
                mu = max(mu * 10.0, 1e-12 * max(abs(f), 1e-30), jump)
            if not accepted and not exact:  # the kept matrix gave no descent: form it afresh
                stored = False
                continue
            if not accepted:
                converged = True  # no descent possible within damping limits: at a (local) minimum
                break
            mu *= 0.3
            decrease = f - f_new
            x, f, h, Rh, r = x_new, f_new, h_new, Rh_new, r_new
            on_bound = u >= 1.0 - 1e-12
            if smooth:
                dx = dx_new
            largest = float(np.abs(step).max())
            if xtol > 0.0 and largest <= xtol:
                converged = True
                break
            if decrease <= tol * max(f, 1e-30):
                if exact:
                    converged = True
                    break
                stored = False  # a kept matrix's small decrease is no proof of a minimum: check with a fresh one
            elif largest > REFRESH_STEP:
                stored = False  # a long step: far from where the kept matrix was formed
        if state is not None and state[0] >= 0:
            state[0] += 1
        p = w.lo + x * (w.hi - w.lo)
        if len(carry):
            carry[1:1 + A], carry[1 + A:1 + 2 * A] = p, x
            carry[1 + 2 * A:1 + 2 * A + H3], carry[1 + 2 * A + H3:] = h, Rh
            carry[0] = 1.0
        fit = max(float(r @ r) + kq, 0.0) * self.scale
        return SolveResult(p=p, residual_rms=float(np.sqrt(fit)), iterations=it, converged=converged,
                           objective=f * self.scale, hidden=h,
                           strain=None if measure is None else measure.measure_hidden(h))


def _gradient(Rb: np.ndarray, W1b: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The exact gradient Jᵀr = W1ᵀ diag(1 − h²) Rᵀ r, per axis block, without forming J: O(r H + H A)."""
    H = Rb.shape[2]
    t = np.matmul(np.swapaxes(Rb, 1, 2), r.reshape(3, -1, 1)).reshape(3, H) * (1.0 - h * h).reshape(3, H)
    return np.matmul(np.swapaxes(W1b, 1, 2), t.reshape(3, H, 1)).reshape(3, -1).sum(axis=0)


def leading_rows(Rb: np.ndarray, W1b: np.ndarray, b1: np.ndarray, xlo: np.ndarray, xhi: np.ndarray, m: int,
                 samples: int = 512, seed: int = 0) -> np.ndarray:
    """Rows R′ (3, m, H) whose Jacobian R′_k diag(1 − h²) W1_k spans most of the residual's,
    J_k = R_k diag(1 − h²) W1_k, over the pose box: the m leading left singular vectors U_k of J_k stacked at
    ``samples`` poses drawn uniformly in [xlo, xhi] (normalized units, fixed ``seed``), as U_kᵀ R_k. The matrix
    formed from them, J_kᵀ U_k U_kᵀ J_k, is the exact one less the Jacobian's weakest directions over the box
    (positive semi-definite, never larger)."""
    _, r, H = Rb.shape
    A = W1b.shape[2]
    x = np.random.default_rng(seed).uniform(xlo, xhi, size=(samples, A))
    hs = np.tanh(x @ W1b.reshape(3 * H, A).T + b1)  # (samples, 3H)
    out = np.empty((3, m, H))
    for k in range(3):
        s = 1.0 - hs[:, k * H:(k + 1) * H] ** 2
        J = np.einsum("ij,nj,ja->ina", Rb[k], s, W1b[k]).reshape(r, samples * A)
        U = np.linalg.svd(J, full_matrices=False)[0]
        out[k] = U[:, :m].T @ Rb[k]
    return np.ascontiguousarray(out)


class HessianReuse:
    """The Gauss-Newton matrix JᵀJ kept across a frame solve's iterations and frames.

    Forming J = R diag(1 − h²) W1 costs O(r H A) per iteration, most of a frame's arithmetic; the gradient Jᵀr costs
    O(r H + H A) without it. Frame to frame at the control rate the pose, and with it JᵀJ, barely changes, so a kept
    matrix still gives a descent direction with the exact gradient (the damped step is checked to lower the
    objective; when it does not, the matrix is formed afresh). It is formed again once it is ``frames`` frames old
    (0: every iteration, plain Gauss-Newton), and after :meth:`forget` (a jump of the warm start)."""

    def __init__(self, n_actuators: int, frames: int, carry_size: int = 0) -> None:
        self.frames = int(frames)
        self.matrix = np.zeros((n_actuators, n_actuators))
        #: the kernels' view: age of ``matrix`` in frames (-1: none kept), the age up to which it is used, and the
        #: count of matrices formed
        self.state = np.array([-1, self.frames, 0], dtype=np.int64)
        #: the last solution kept for a frame warm-started from it (:func:`models._skin_kernels.solve_frame`'s
        #: layout, :attr:`KsnnInverse.carry_size` long; empty: none kept)
        self.carry = np.zeros(int(carry_size))

    @property
    def formed(self) -> int:
        """Gauss-Newton matrices formed so far."""
        return int(self.state[2])

    def forget(self) -> None:
        """Form the matrix afresh on the next solve, and keep no solution for it."""
        self.state[0] = -1
        if len(self.carry):
            self.carry[0] = 0.0


class FrameSolve:
    """One control frame's inverse solve with its settings bound: face-unit channel values → actuator values, the
    residual and the strain guard's reduced measure of the solution, in one compiled call; with ``guard_steps``
    also the guard's verdict, and its search from the warm start toward a solution that leaves the strain range
    (:meth:`models.strain_guard.StrainGuard.limit` with that many bisections), so that a limited frame costs no
    second call.

    Built once (:meth:`KsnnInverse.frame_solve`) so that a frame gathers no arguments and allocates no inputs: a value
    is clamped to 0..1 and a non-finite one (NaN: not set) counts as 0, as the weights of :meth:`KsnnInverse.solve`;
    the solve is warm-started from the previous pose with the inverse's smoothness. The last call's residual,
    iterations and strain are attributes, valid until the next call. Without the compiled kernels it runs the same
    steps through :meth:`KsnnInverse.solve` in numpy.
    """

    def __init__(self, inverse: KsnnInverse, max_iterations: int, tol: float, xtol: float,
                 measure: StrainGuard, reuse_frames: int = 0, guard_steps: int | None = None) -> None:
        n = inverse.n_units
        self.inverse = inverse
        self.measure = measure
        self.max_iterations = int(max_iterations)
        self.tol = float(tol)
        self.xtol = float(xtol)
        self.values = np.full(n, np.nan)  # the channel values being solved (the caller may fill this buffer)
        self.weights = np.zeros(n)  # the face-unit weights they gave
        self.residual_rms = 0.0  # m, of the last solve
        self.iterations = 0
        self.strain: tuple[float, float] = (0.0, 0.0)  # the guard's reduced measure (min, max) at the last pose
        self.guard_steps = guard_steps
        self.verdict = "ok"  # the guard's on the last pose: ok, limited, held (always ok without guard_steps)
        self.reuse = inverse.frame_state(reuse_frames)  # the Gauss-Newton matrix and solution kept frame to frame
        self._scale = inverse.scale
        self._kernel = None
        self.kernel_args: tuple[np.ndarray, ...] = ()  # what the compiled call takes after values, weights, poses
        if inverse.compiled and measure.compiled:
            from models.kernel_args import pack_frame_args
            from models.kernels_aot import kernel

            self._kernel = kernel("solve_values_measured")
            self.kernel_args = pack_frame_args((*inverse.kernel_arrays(), self.max_iterations, self.tol, self.xtol),
                                               measure.kernel_arrays(),
                                               None if guard_steps is None else measure.search_args(guard_steps))
        # the compiled call writes the pose into whichever of these the start is not
        self._poses = (np.empty(len(inverse.lo)), np.empty(len(inverse.lo)))

    def __call__(self, values: np.ndarray, p_prev: np.ndarray) -> np.ndarray:
        """The actuator values (raw SI) for channel ``values`` (one per face unit, in unit order; NaN: not set),
        warm-started from the pose ``p_prev`` (float64). The array is this solve's own, reused by the call after
        next: it may be the next call's ``p_prev``; copy it to keep it longer."""
        buf = self.values
        if values is not buf:  # copied: the compiled call then always sees a writable float64 vector of its own
            if values.shape != buf.shape:
                raise ValueError(f"need {buf.shape[0]} face-unit values, got shape {values.shape}")
            buf[:] = values
        if self._kernel is not None:
            a, b = self._poses
            p = b if p_prev is a else a
            fit, it, s_lo, s_hi, verdict = self._kernel(buf, self.weights, p_prev, p, self.reuse.matrix,
                                                        self.reuse.state, self.reuse.carry, *self.kernel_args)
            self.residual_rms = math.sqrt(fit * self._scale)
            self.iterations = it
            self.strain = (s_lo, s_hi)
            self.verdict = VERDICTS[verdict] if verdict >= 0 else "ok"
            return p
        w = self.weights
        np.clip(buf, 0.0, 1.0, out=w)
        w[~np.isfinite(buf)] = 0.0
        res = self.inverse.solve(w, p_prev=p_prev, max_iterations=self.max_iterations, tol=self.tol, xtol=self.xtol,
                                 measure=self.measure, reuse=self.reuse)
        self.residual_rms = res.residual_rms
        self.iterations = res.iterations
        self.strain = res.strain if res.strain is not None else self.measure.measure(res.p)
        self.verdict = "ok"
        if self.guard_steps is not None and not self.measure.passes(self.strain):
            pose, self.verdict = self.measure.limit(p_prev, res.p, self.guard_steps)
            self.strain = self.measure.measure(pose)
            return pose
        return res.p


def _dposv() -> Any:
    """LAPACK's ``dposv`` (scipy), imported on the numpy path's first use: the compiled path never needs scipy.linalg,
    whose import costs the loop process about 25 MiB."""
    from scipy.linalg.lapack import dposv

    return dposv
