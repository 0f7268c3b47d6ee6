"""Homogeneous uniaxial tension/compression with zero lateral stress, in closed form (plus a scalar root find).

With frictionless grips a uniaxial specimen deforms homogeneously, F = diag(λ, l, l), so this answer IS the FEM
answer (linear and quadratic tets reproduce affine fields exactly). It is the cheap surrogate used when fitting.

For the principal stretches (λ1, λ2, λ3) of an isochoric-split energy Ψ = W(Ī1, Ī2) + κ/2 (J − 1)², the principal
first Piola–Kirchhoff stresses are

    P_i = W_1 ∂Ī1/∂λ_i + W_2 ∂Ī2/∂λ_i + κ (J − 1) J / λ_i,
    ∂Ī1/∂λ_i = J^(-2/3) 2 λ_i − (2/3) Ī1 / λ_i,
    ∂Ī2/∂λ_i = J^(-4/3) 2 λ_i (λ_j² + λ_k²) − (4/3) Ī2 / λ_i.

The lateral stretch l solves P_2(λ, l, l) = 0 (safeguarded Newton on log l, vectorised over all stretches); the
nominal (engineering) stress is P_1 and the axial force is P_1 times the undeformed cross-section.
"""

from __future__ import annotations

import numpy as np

from offline.material.models import MaterialParams


def _w_derivatives(params: MaterialParams, i1b: np.ndarray, i2b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """∂W/∂Ī1 and ∂W/∂Ī2 of the model's isochoric energy (arrays; complex-safe)."""
    c = params.coefficients()
    if params.model == "neo_hookean":
        return 0.5 * c["mu"] + 0.0 * i1b, 0.0 * i2b
    if params.model == "mooney_rivlin":
        return c["c10"] + 0.0 * i1b, c["c01"] + 0.0 * i2b
    d = i1b - 3.0
    return c["c10"] + 2.0 * c["c20"] * d + 3.0 * c["c30"] * d * d, 0.0 * i2b


def principal_piola(params: MaterialParams, l1: np.ndarray, l2: np.ndarray, l3: np.ndarray) -> np.ndarray:
    """Principal first Piola–Kirchhoff stresses (Pa), shape (3, ...), for principal stretches l1, l2, l3."""
    kappa = params.coefficients()["kappa"]
    J = l1 * l2 * l3
    jm23 = J ** (-2.0 / 3.0)
    jm43 = jm23 * jm23
    sq = (l1 * l1, l2 * l2, l3 * l3)
    i1b = jm23 * (sq[0] + sq[1] + sq[2])
    i2b = jm43 * (sq[0] * sq[1] + sq[1] * sq[2] + sq[2] * sq[0])
    w1, w2 = _w_derivatives(params, i1b, i2b)
    out = []
    for i, lam in enumerate((l1, l2, l3)):
        others = sq[(i + 1) % 3] + sq[(i + 2) % 3]
        d1 = jm23 * 2.0 * lam - (2.0 / 3.0) * i1b / lam
        d2 = jm43 * 2.0 * lam * others - (4.0 / 3.0) * i2b / lam
        out.append(w1 * d1 + w2 * d2 + kappa * (J - 1.0) * J / lam)
    return np.stack(out)


def _lateral_residual(params: MaterialParams, lam: np.ndarray, lat: np.ndarray) -> np.ndarray:
    return principal_piola(params, lam, lat, lat)[1]


def lateral_stretch(params: MaterialParams, stretch: np.ndarray, *, tol: float = 1e-13) -> np.ndarray:
    """Lateral stretch l(λ) at zero lateral stress for each axial stretch λ (vectorised safeguarded Newton).

    Returns NaN where no root exists in l ∈ [1e-3, 1e3] (an unstable parameter set, e.g. a Yeoh model softening
    to negative stiffness).
    """
    lam = np.asarray(stretch, dtype=float)
    if np.any(~np.isfinite(lam)) or np.any(lam <= 0.0):
        raise ValueError("axial stretches must be finite and positive")
    lo = np.full(lam.shape, np.log(1e-3))
    hi = np.full(lam.shape, np.log(1e3))
    g_lo = _lateral_residual(params, lam, np.exp(lo))
    g_hi = _lateral_residual(params, lam, np.exp(hi))
    bracketed = (g_lo < 0.0) & (g_hi > 0.0)
    nu0 = min(max(params.nu, 0.0), 0.5)
    s = np.clip(-nu0 * np.log(lam), lo, hi)  # small-strain guess l = λ^(-ν)
    h = 1e-20
    for _ in range(100):
        gc = _lateral_residual(params, lam.astype(complex), np.exp(s + 1j * h))
        g = gc.real
        dg = gc.imag / h
        neg = g < 0.0
        lo = np.where(neg, s, lo)
        hi = np.where(neg, hi, s)
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = s - g / dg
        ok = np.isfinite(newton) & (newton >= lo) & (newton <= hi)
        s_new = np.where(ok, newton, 0.5 * (lo + hi))
        step = np.abs(s_new - s)
        s = s_new
        if np.all(step[bracketed] < tol):
            break
    return np.where(bracketed, np.exp(s), np.nan)


def uniaxial_nominal_stress(params: MaterialParams, stretch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nominal axial stress in Pa, lateral stretch) for axial stretches λ = 1 + ε with zero lateral stress."""
    lam = np.asarray(stretch, dtype=float)
    lat = lateral_stretch(params, lam)
    p = principal_piola(params, lam, lat, lat)[0]
    return p, lat


def uniaxial_force(params: MaterialParams, strain: np.ndarray, area: float) -> np.ndarray:
    """Axial force (N) of a homogeneous specimen of undeformed cross-section ``area`` (m²) at nominal strains."""
    eps = np.asarray(strain, dtype=float)
    return uniaxial_nominal_stress(params, 1.0 + eps)[0] * area
