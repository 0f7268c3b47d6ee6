"""Moving-least-squares interpolation of sparse height samples and sample placement from a density map.

At a point u the MLS value is a(u)ᵀ (1, u) with a(u) the affine fit minimising Σ_s θ(|u − u_s|) (a(u)ᵀ (1, u_s) − h_s)²
and θ(r) = exp(−(r/σ)²) a Gaussian of width σ. The value is linear in the sample heights, so a whole set of
evaluation points gives a fixed matrix Φ (points × samples) that reproduces every affine height field exactly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def mls_matrix(points: np.ndarray, samples: np.ndarray, width: float) -> np.ndarray:
    """Φ (P, S): heights at ``points`` (P, d) = Φ @ heights at ``samples`` (S, d), affine MLS of kernel width σ.

    Raises ValueError when a point sees too few samples within a few widths to fit an affine function (the kernel
    is too narrow for the sample spacing).
    """
    pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
    smp = np.atleast_2d(np.asarray(samples, dtype=np.float64))
    if pts.shape[1] != smp.shape[1]:
        raise ValueError(f"points are {pts.shape[1]}-D but samples are {smp.shape[1]}-D")
    if not (np.isfinite(width) and width > 0):
        raise ValueError(f"MLS kernel width must be > 0, got {width}")
    d = pts.shape[1]
    if smp.shape[0] < d + 1:
        raise ValueError(f"affine MLS in {d}-D needs at least {d + 1} samples, got {smp.shape[0]}")
    P = np.hstack([np.ones((smp.shape[0], 1)), smp])  # (S, d+1)
    r2 = ((pts[:, None, :] - smp[None, :, :]) ** 2).sum(-1)
    theta = np.exp(-r2 / width ** 2)  # (P, S)
    M = np.einsum("ps,si,sj->pij", theta, P, P)  # moment matrices (P, d+1, d+1)
    cond = np.linalg.cond(M)
    if not np.all(cond < 1e12):
        bad = int(np.argmax(cond))
        raise ValueError(f"MLS fit is ill-conditioned at point {bad} {pts[bad]} (condition {cond[bad]:.2e}): "
                         f"widen the kernel (width {width}) or add samples near it")
    q = np.hstack([np.ones((pts.shape[0], 1)), pts])  # (P, d+1)
    c = np.linalg.solve(M, q[:, :, None])[:, :, 0]  # M⁻¹ q(u)
    return theta * (c @ P.T)


def place_samples(candidates: np.ndarray, density: Callable[[np.ndarray], np.ndarray] | np.ndarray,
                  count: int) -> np.ndarray:
    """Indices of ``count`` candidates spread by density: greedy farthest-point sampling of distance × √density.

    Each pick maximises (distance to the picked set) · √ρ, so spacing scales like 1/√ρ: samples are denser where
    the density map is larger. Deterministic (starts from the densest candidate).
    """
    cand = np.atleast_2d(np.asarray(candidates, dtype=np.float64))
    rho = np.asarray(density(cand) if callable(density) else density, dtype=np.float64).reshape(-1)
    if rho.shape[0] != cand.shape[0]:
        raise ValueError(f"density has {rho.shape[0]} values for {cand.shape[0]} candidates")
    if not np.all(np.isfinite(rho)) or np.any(rho <= 0):
        raise ValueError("density map values must be finite and > 0")
    if not (1 <= count <= cand.shape[0]):
        raise ValueError(f"sample count must be in [1, {cand.shape[0]}] (the candidates), got {count}")
    w = np.sqrt(rho)
    picked = [int(np.argmax(rho))]
    dist = np.linalg.norm(cand - cand[picked[0]], axis=1)
    for _ in range(count - 1):
        k = int(np.argmax(dist * w))
        picked.append(k)
        dist = np.minimum(dist, np.linalg.norm(cand - cand[k], axis=1))
    return np.array(picked, dtype=np.int64)
