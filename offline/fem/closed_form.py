"""Closed-form homogeneous answers used to validate the FEM and to fit materials to tensile tests.

Uniaxial stress: F = diag(λ, l, l) with the lateral stretch l solved from zero lateral stress (scalar root find);
the nominal (first Piola-Kirchhoff) stress along the load is returned. Works for every :class:`Material`.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq

from .materials import Material, first_piola, neo_hookean


def uniaxial(material: Material, stretch: float) -> tuple[float, float]:
    """(nominal stress P11 in Pa, lateral stretch l) for homogeneous uniaxial stress at axial stretch λ > 0."""
    lam = float(stretch)
    if not lam > 0:
        raise ValueError(f"stretch must be > 0, got {stretch}")

    def lateral_stress(lat: float) -> float:
        return float(first_piola(material, np.diag([lam, lat, lat]))[1, 1])

    lo, hi = 1e-3, 1e3
    lat = brentq(lateral_stress, lo, hi, xtol=1e-15, rtol=1e-14, maxiter=200)
    return float(first_piola(material, np.diag([lam, lat, lat]))[0, 0]), float(lat)


def uniaxial_neo_hookean(mu: float, kappa: float, stretch: float) -> tuple[float, float]:
    """(nominal stress, lateral stretch) of the compressible neo-Hookean Ψ = μ/2 (Ī1 − 3) + κ/2 (J − 1)²."""
    return uniaxial(neo_hookean(mu, kappa), stretch)

