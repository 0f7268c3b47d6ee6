"""Which fitted parameters the data identify: confidence intervals from the residual Jacobian at the estimate.

The covariance of the optimiser vector (log10 E, ν, shape parameters) is s² (JᵀJ)⁺ with s² = |r|² / (n − p), the
usual linearised least-squares estimate; the 95 % interval is the estimate ± t(0.975, n − p) standard errors
(for E taken in log10 E, so the interval is positive and asymmetric). A parameter counts as identified when its
95 % interval spans less than half of the range the fit allowed it and the estimate does not sit on a bound.
Uniaxial tension of a near-incompressible rubber pins E but hardly ν: the force barely changes with ν over the
allowed range, so ν stays unidentified unless compression (or lateral-strain) data join the fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

#: An interval narrower than this fraction of the allowed range counts as identified.
IDENTIFIED_FRACTION = 0.5


def _jacobian(residual: Callable[[np.ndarray], np.ndarray], x: np.ndarray, lower: np.ndarray,
              upper: np.ndarray) -> np.ndarray:
    """Central differences inside the box (one-sided at a bound), step 1e-5 of each parameter's range."""
    r0 = residual(x)
    J = np.empty((r0.size, x.size))
    for i in range(x.size):
        h = 1e-5 * (upper[i] - lower[i])
        lo, hi = max(x[i] - h, lower[i]), min(x[i] + h, upper[i])
        xp, xm = x.copy(), x.copy()
        xp[i], xm[i] = hi, lo
        J[:, i] = (residual(xp) - residual(xm)) / (hi - lo)
    return J


def identifiability(names: tuple[str, ...], x: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                    residual: Callable[[np.ndarray], np.ndarray], strain: np.ndarray,
                    fixed_nu: float | None = None) -> dict[str, Any]:
    """Per-parameter estimate, standard error, 95 % interval, allowed range and whether the data identify it.

    ``names``/``x``/``lower``/``upper`` describe the optimiser vector (``log10_E`` first); ``residual`` is the
    scaled residual the fit minimised; ``strain`` the fitted strains (to say whether the data were tension-only).
    """
    from scipy import stats

    x = np.asarray(x, dtype=float)
    r = residual(x)
    n, p = r.size, x.size
    J = _jacobian(residual, x, lower, upper)
    dof = n - p
    out: dict[str, Any] = {"method": "linearised least squares at the estimate: cov = s² (JᵀJ)⁺, 95 % t interval",
                           "n_points": int(n), "n_parameters": int(p), "parameters": {}}
    if dof < 1:
        out["note"] = f"{n} points for {p} parameters: no degrees of freedom left for an error estimate"
        return out
    s2 = float(r @ r) / dof
    cov = np.linalg.pinv(J.T @ J) * s2
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    t = float(stats.t.ppf(0.975, dof))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    for i, name in enumerate(names):
        span = float(upper[i] - lower[i])
        at_bound = bool(min(x[i] - lower[i], upper[i] - x[i]) <= 1e-6 * span)
        identified = bool(2 * t * sd[i] < IDENTIFIED_FRACTION * span and not at_bound and np.isfinite(sd[i]))
        if name == "log10_E":
            entry = {"estimate": 10 ** x[i], "stderr": 10 ** x[i] * math.log(10) * sd[i],
                     "ci95": [10 ** (x[i] - t * sd[i]), 10 ** (x[i] + t * sd[i])],
                     "allowed": [10 ** lower[i], 10 ** upper[i]], "unit": "Pa"}
            key = "E"
        else:
            entry = {"estimate": float(x[i]), "stderr": float(sd[i]),
                     "ci95": [float(x[i] - t * sd[i]), float(x[i] + t * sd[i])],
                     "allowed": [float(lower[i]), float(upper[i])]}
            key = name
        entry.update(at_bound=at_bound, identified=identified)
        out["parameters"][key] = entry
    out["correlation"] = {"names": ["E" if k == "log10_E" else k for k in names],
                          "matrix": np.round(np.nan_to_num(corr), 4).tolist()}
    out["summary"] = _summary(out["parameters"], np.asarray(strain), fixed_nu)
    return out


def _summary(params: dict[str, Any], strain: np.ndarray, fixed_nu: float | None) -> list[str]:
    lines = []
    kind = ("tension-only" if np.all(strain >= 0) else "compression-only" if np.all(strain <= 0)
            else "tension and compression")
    if fixed_nu is not None:
        lines.append(f"nu was fixed at {fixed_nu:g} by the caller, not fitted")
    for name, e in params.items():
        lo, hi = e["ci95"]
        if e["identified"]:
            lines.append(f"{name} is identified by these {kind} data: 95 % interval [{lo:.4g}, {hi:.4g}]")
        else:
            why = "the estimate sits on a bound of its allowed range" if e["at_bound"] else \
                "its 95 % interval spans more than half of its allowed range"
            lines.append(f"{name} is NOT identified by these {kind} data ({why}: estimate {e['estimate']:.4g}, "
                         f"95 % interval [{lo:.4g}, {hi:.4g}], allowed {e['allowed'][0]:.4g}..{e['allowed'][1]:.4g})")
    if "nu" in params and not params["nu"]["identified"] and kind == "tension-only":
        lines.append("tension-only data do not pin nu: add compression (cylinder) data to fit jointly, or fix nu "
                     "with --nu-range V:V from another source")
    return lines
