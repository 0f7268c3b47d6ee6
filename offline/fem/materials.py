"""Compressible hyperelastic materials with an isochoric/volumetric split (silicone skin).

All models share one energy density form, which the numba kernels evaluate from a 5-vector of coefficients:

    Ψ = c10 (Ī1 − 3) + c20 (Ī1 − 3)² + c30 (Ī1 − 3)³ + c01 (Ī2 − 3) + κ/2 (J − 1)²,
    Ī1 = J^(-2/3) tr C,  Ī2 = J^(-4/3) ½((tr C)² − tr C²).

neo-Hookean is c10 = μ/2; Mooney-Rivlin uses c10, c01; Yeoh uses c10, c20, c30. The small-strain shear modulus is
μ = 2 (c10 + c01) and the bulk modulus κ. :func:`first_piola` and :func:`energy_density` are plain NumPy references
(used by tests and closed-form checks), independent of the kernels.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

#: Parameter names each material model requires.
MODEL_PARAMS: dict[str, tuple[str, ...]] = {
    "neo_hookean": ("mu", "kappa"),
    "mooney_rivlin": ("c10", "c01", "kappa"),
    "yeoh": ("c10", "c20", "c30", "kappa"),
}


@dataclass(frozen=True)
class Material:
    """A named hyperelastic model (see :data:`MODEL_PARAMS`) with its parameters (Pa) and density (kg/m³)."""

    name: str
    params: Mapping[str, float] = field(default_factory=dict)
    density: float = 1070.0

    def __post_init__(self) -> None:
        if self.name not in MODEL_PARAMS:
            raise ValueError(f"unknown material model {self.name!r}; known: {sorted(MODEL_PARAMS)}")
        params = {str(k): float(v) for k, v in dict(self.params).items()}
        missing = [k for k in MODEL_PARAMS[self.name] if k not in params]
        if missing:
            raise ValueError(f"material {self.name!r}: missing parameter(s) {missing}")
        extra = [k for k in params if k not in MODEL_PARAMS[self.name]]
        if extra:
            raise ValueError(f"material {self.name!r}: unknown parameter(s) {extra}")
        for k, v in params.items():
            if not np.isfinite(v):
                raise ValueError(f"material {self.name!r}: parameter {k}={v} is not finite")
        if params["kappa"] <= 0:
            raise ValueError(f"material {self.name!r}: kappa must be > 0, got {params['kappa']}")
        if not (np.isfinite(self.density) and self.density > 0):
            raise ValueError(f"material {self.name!r}: density must be > 0, got {self.density}")
        object.__setattr__(self, "params", MappingProxyType(params))
        object.__setattr__(self, "density", float(self.density))

    @property
    def coefficients(self) -> np.ndarray:
        """(c10, c20, c30, c01, kappa) of the shared energy form, as the kernels take them."""
        p = self.params
        if self.name == "neo_hookean":
            return np.array([0.5 * p["mu"], 0.0, 0.0, 0.0, p["kappa"]])
        if self.name == "mooney_rivlin":
            return np.array([p["c10"], 0.0, 0.0, p["c01"], p["kappa"]])
        return np.array([p["c10"], p["c20"], p["c30"], 0.0, p["kappa"]])

    @property
    def shear_modulus(self) -> float:
        """Small-strain shear modulus μ = 2 (c10 + c01)."""
        c = self.coefficients
        return float(2.0 * (c[0] + c[3]))

    @property
    def bulk_modulus(self) -> float:
        """Small-strain bulk modulus κ."""
        return float(self.params["kappa"])


def neo_hookean(mu: float, kappa: float, density: float = 1070.0) -> Material:
    """Compressible neo-Hookean: Ψ = μ/2 (J^(-2/3) tr C − 3) + κ/2 (J − 1)²."""
    if mu <= 0:
        raise ValueError(f"neo_hookean: mu must be > 0, got {mu}")
    return Material("neo_hookean", {"mu": mu, "kappa": kappa}, density)


def mu_kappa_from_E_nu(E: float, nu: float) -> tuple[float, float]:
    """Shear and bulk modulus from Young's modulus and Poisson's ratio (−1 < ν < 0.5)."""
    if E <= 0 or not (-1.0 < nu < 0.5):
        raise ValueError(f"need E > 0 and -1 < nu < 0.5, got E={E}, nu={nu}")
    return E / (2.0 * (1.0 + nu)), E / (3.0 * (1.0 - 2.0 * nu))


def E_nu_from_mu_kappa(mu: float, kappa: float) -> tuple[float, float]:
    """Young's modulus E = 9μκ/(3κ+μ) and Poisson's ratio ν = (3κ−2μ)/(2(3κ+μ))."""
    if mu <= 0 or kappa <= 0:
        raise ValueError(f"need mu > 0 and kappa > 0, got mu={mu}, kappa={kappa}")
    return 9.0 * mu * kappa / (3.0 * kappa + mu), (3.0 * kappa - 2.0 * mu) / (2.0 * (3.0 * kappa + mu))


def neo_hookean_from_E_nu(E: float, nu: float, density: float = 1070.0) -> Material:
    """neo-Hookean material from small-strain E and ν."""
    mu, kappa = mu_kappa_from_E_nu(E, nu)
    return neo_hookean(mu, kappa, density)


def mooney_rivlin(c10: float, c01: float, kappa: float, density: float = 1070.0) -> Material:
    """Compressible Mooney-Rivlin: Ψ = c10 (Ī1 − 3) + c01 (Ī2 − 3) + κ/2 (J − 1)²."""
    return Material("mooney_rivlin", {"c10": c10, "c01": c01, "kappa": kappa}, density)


def yeoh(c10: float, c20: float, c30: float, kappa: float, density: float = 1070.0) -> Material:
    """Compressible Yeoh: Ψ = Σ ci0 (Ī1 − 3)^i + κ/2 (J − 1)²."""
    return Material("yeoh", {"c10": c10, "c20": c20, "c30": c30, "kappa": kappa}, density)


def _invariants(F: np.ndarray):
    C = np.swapaxes(F, -1, -2) @ F
    I1 = np.trace(C, axis1=-2, axis2=-1)
    I2 = 0.5 * (I1 ** 2 - np.einsum("...ij,...ij->...", C, C))
    J = np.linalg.det(F)
    return C, I1, I2, J


def energy_density(material: Material, F: np.ndarray) -> np.ndarray:
    """Ψ(F) per unit rest volume for deformation gradients F (..., 3, 3) (NumPy reference)."""
    F = np.asarray(F, dtype=np.float64)
    c10, c20, c30, c01, kappa = material.coefficients
    _, I1, I2, J = _invariants(F)
    a = I1 * J ** (-2.0 / 3.0) - 3.0
    b = I2 * J ** (-4.0 / 3.0) - 3.0
    return c10 * a + c20 * a ** 2 + c30 * a ** 3 + c01 * b + 0.5 * kappa * (J - 1.0) ** 2


def first_piola(material: Material, F: np.ndarray) -> np.ndarray:
    """First Piola-Kirchhoff stress P = ∂Ψ/∂F (..., 3, 3) (NumPy reference)."""
    F = np.asarray(F, dtype=np.float64)
    c10, c20, c30, c01, kappa = material.coefficients
    C, I1, I2, J = _invariants(F)
    FinvT = np.swapaxes(np.linalg.inv(F), -1, -2)
    j23, j43 = J ** (-2.0 / 3.0), J ** (-4.0 / 3.0)
    a = I1 * j23 - 3.0
    dpsi1 = c10 + 2.0 * c20 * a + 3.0 * c30 * a ** 2
    ex = (..., None, None)
    dI1bar = j23[ex] * (2.0 * F - (2.0 / 3.0) * I1[ex] * FinvT)
    dI2bar = j43[ex] * (2.0 * (I1[ex] * F - F @ C) - (4.0 / 3.0) * I2[ex] * FinvT)
    dvol = (kappa * (J - 1.0) * J)[ex] * FinvT
    return dpsi1[ex] * dI1bar + c01 * dI2bar + dvol
