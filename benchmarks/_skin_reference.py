"""The skin ARKit frame solve as it was before the reduced guard: the reference the ``skin_solve`` benchmark compares
against in the same run (hidden-space inverse with per-iteration active-set indexing and ``numpy.linalg.solve``;
strain guard = a full predictor pass and the extreme principal strain over all triangles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.predictor import KsnnWeights


@dataclass(frozen=True)
class ReferenceResult:
    """One inverse solve: actuator values (raw SI units), RMS surface residual (m), iterations, convergence."""

    p: np.ndarray
    residual_rms: float
    iterations: int
    converged: bool
    objective: float


class ReferenceInverse:
    """Precomputed hidden-space inverse of one KSNN for one set of face units and vertex weights.

    ``face_units`` (U, V, 3) are target offsets per unit weight; ``vertex_weights`` (V,) select/weight surface
    vertices (default 1). ``smoothness`` weighs ‖p̂ − p̂_prev‖² against the mean squared vertex error (m²):
    the default makes a full-range jump of one actuator cost as much as 0.3 mm RMS surface error.
    """

    def __init__(self, weights: KsnnWeights, face_units: np.ndarray, vertex_weights: np.ndarray | None = None,
                 smoothness: float = (0.3e-3) ** 2, damping: float = 1e-12, lo: np.ndarray | None = None,
                 hi: np.ndarray | None = None) -> None:
        w = weights
        n_vert = w.n_vertices
        fu = np.asarray(face_units, dtype=np.float64)
        if fu.ndim != 3 or fu.shape[1:] != (n_vert, 3):
            raise ValueError(f"face_units must have shape (U, {n_vert}, 3), got {fu.shape}")
        s2 = np.ones(n_vert) if vertex_weights is None else np.asarray(vertex_weights, dtype=np.float64) ** 2
        if s2.shape != (n_vert,) or not np.all(np.isfinite(s2)) or s2.sum() <= 0:
            raise ValueError(f"vertex_weights must be ({n_vert},) finite with a positive sum")
        self.weights = w
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
        R = np.zeros((3 * H, 3 * H))
        P = np.zeros((3 * H, 3 * H))
        q0 = np.zeros(3 * H)
        Qd = np.zeros((3 * H, self.n_units))
        const_b = 0.0
        e = np.zeros(self.n_units)
        M = np.zeros((self.n_units, self.n_units))
        for k in range(3):
            sl = slice(k * H, (k + 1) * H)
            W2s = w.W2[k] * s2[None, :]  # (H, V)
            G = W2s @ w.W2[k].T
            c = W2s @ w.b2[k]
            D = W2s @ fu[:, :, k].T  # (H, U)
            lam, Q = np.linalg.eigh(G)
            keep = lam > lam.max() * 1e-12
            sq = np.sqrt(np.where(keep, lam, 1.0))
            Rk = (Q * np.where(keep, sq, 0.0)).T  # R_kᵀ R_k = G
            Pk = (Q * np.where(keep, 1.0 / sq, 0.0)).T  # maps c − D w to q
            R[sl, sl] = Rk
            P[sl, sl] = Pk
            q0[sl] = Pk @ c
            Qd[sl] = Pk @ D
            const_b += float(w.b2[k] @ (s2 * w.b2[k]))
            fs = fu[:, :, k] * s2[None, :]
            e += fs @ w.b2[k]
            M += fs @ fu[:, :, k].T
        self._R = R
        self._q0 = q0
        self._Qd = Qd
        self._const_b = const_b
        self._e = e
        self._M = M
        self._W1 = np.concatenate([w.W1[k].T for k in range(3)], axis=0)  # (3H, A)
        self._b1 = np.concatenate(list(w.b1))
        self._eye = np.eye(A)

    # ------------------------------------------------------------------ pieces
    def _q(self, wts: np.ndarray) -> tuple[np.ndarray, float]:
        q = self._q0 - self._Qd @ wts
        const = self._const_b - 2.0 * wts @ self._e + wts @ self._M @ wts - q @ q
        return q, const

    def surface_error(self, p: np.ndarray, unit_weights: np.ndarray) -> float:
        """Exact mean squared weighted vertex error (m²) of the prediction at raw pose p vs the target."""
        q, const = self._q(np.asarray(unit_weights, dtype=np.float64))
        h = np.tanh(self._W1 @ self.weights.normalize(p) + self._b1)
        r = self._R @ h + q
        return max(float(r @ r + const), 0.0) * self.scale

    def solve(self, unit_weights: np.ndarray, p_prev: np.ndarray | None = None, p0: np.ndarray | None = None,
              max_iterations: int = 20, tol: float = 1e-9) -> ReferenceResult:
        """Damped, projected Gauss-Newton from ``p0`` (default ``p_prev``, else mid-range) for face-unit weights.

        ``tol`` bounds the relative decrease of the objective that counts as converged.
        """
        wts = np.asarray(unit_weights, dtype=np.float64)
        if wts.shape != (self.n_units,) or not np.all(np.isfinite(wts)):
            raise ValueError(f"unit_weights must be {self.n_units} finite numbers, got shape {wts.shape}")
        q, const = self._q(wts)
        w = self.weights
        xlo, xhi = self._xlo, self._xhi
        x_prev = None if p_prev is None else w.normalize(p_prev)
        start = p0 if p0 is not None else p_prev
        x = np.full(w.n_actuators, 0.5) if start is None else w.normalize(start)
        x = np.clip(x, xlo, xhi)
        lam_s = self.smoothness / self.scale  # in the unscaled objective

        def objective(xv: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
            h = np.tanh(self._W1 @ xv + self._b1)
            r = self._R @ h + q
            f = float(r @ r + const)
            if x_prev is not None:
                d = xv - x_prev
                f += lam_s * float(d @ d)
            return f, h, r

        f, h, r = objective(x)
        mu = self.damping / self.scale
        converged = False
        it = 0
        for it in range(1, max_iterations + 1):  # noqa: B007 - it is reported
            J = self._R @ ((1.0 - h * h)[:, None] * self._W1)  # (3H, A)
            g = J.T @ r
            Hm = J.T @ J
            if x_prev is not None:
                g = g + lam_s * (x - x_prev)
                Hm = Hm + lam_s * self._eye
            # Active set: variables at a bound whose gradient pushes outward stay fixed.
            free = ~(((x <= xlo) & (g > 0)) | ((x >= xhi) & (g < 0)))
            if not free.any():
                converged = True
                break
            accepted = False
            all_free = bool(free.all())
            Hf0 = Hm if all_free else Hm[np.ix_(free, free)]
            gf = g if all_free else g[free]
            eye = self._eye if all_free else np.eye(int(free.sum()))
            reg = 1e-14 * float(np.trace(Hm))
            for _ in range(8):
                step = np.zeros_like(x)
                step[free] = -np.linalg.solve(Hf0 + (mu + reg) * eye, gf)
                x_new = np.clip(x + step, xlo, xhi)
                f_new, h_new, r_new = objective(x_new)
                if f_new <= f:
                    accepted = True
                    break
                mu = max(mu * 10.0, 1e-12 * max(abs(f), 1e-30))
            if not accepted:
                converged = True  # no descent possible within damping limits: at a (local) minimum
                break
            mu *= 0.3
            decrease = f - f_new
            step = x_new - x
            x, f, h, r = x_new, f_new, h_new, r_new
            if decrease <= tol * max(f, 1e-30) or float(np.max(np.abs(step))) < 1e-12:
                converged = True
                break
        p = w.lo + x * (w.hi - w.lo)
        fit = max(float(r @ r + const), 0.0) * self.scale
        return ReferenceResult(p=p, residual_rms=float(np.sqrt(fit)), iterations=it, converged=converged,
                           objective=f * self.scale)


def reference_guard_ok(predictor, p: np.ndarray, strain_range: tuple[float, float] = (-0.2, 0.5)) -> bool:
    """The previous in-loop guard check: full predictor pass, extreme principal strain over all triangles."""
    lo, hi = predictor.strain_extremes(predictor.predict(p))
    return strain_range[0] <= lo and hi <= strain_range[1]
