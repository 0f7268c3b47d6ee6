"""Hyperelastic models that can be fitted, each described by its small-strain (E, ν) plus shape parameters.

All three are the compressible, isochoric-split energies of :mod:`offline.fem.materials`:

- neo-Hookean      Ψ = μ/2 (Ī1 − 3) + κ/2 (J − 1)²
- Mooney-Rivlin    Ψ = c10 (Ī1 − 3) + c01 (Ī2 − 3) + κ/2 (J − 1)²
- Yeoh             Ψ = c10 (Ī1 − 3) + c20 (Ī1 − 3)² + c30 (Ī1 − 3)³ + κ/2 (J − 1)²

Every model is parameterised by the Young's modulus E and Poisson's ratio ν of its small-strain limit
(μ = E / (2(1 + ν)), κ = E / (3(1 − 2ν))), so E and ν mean the same thing whichever model is fitted. The extra
parameters shape the large-strain response: Mooney-Rivlin takes ``c01`` (Pa; then c10 = μ/2 − c01), Yeoh takes
``c20`` and ``c30`` (Pa; c10 = μ/2).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from models.material import MATERIAL_MODELS, SHAPE_PARAMS, SkinMaterial, canonical_material_model

MODEL_NAMES: tuple[str, ...] = MATERIAL_MODELS

NU_RANGE: tuple[float, float] = (0.3, 0.499)
"""Realistic Poisson's ratio range for filled/unfilled silicone rubbers, used as fit bounds."""

_EXTRA_PARAMS = SHAPE_PARAMS


def canonical_model_name(name: str) -> str:
    """Return the canonical model name for ``name`` (see :mod:`models.material`), or raise ValueError."""
    return canonical_material_model(name)


def mu_kappa_from_E_nu(E: float, nu: float) -> tuple[float, float]:
    """Small-strain shear and bulk moduli (Pa) from Young's modulus (Pa) and Poisson's ratio."""
    return E / (2.0 * (1.0 + nu)), E / (3.0 * (1.0 - 2.0 * nu))


def E_nu_from_mu_kappa(mu: float, kappa: float) -> tuple[float, float]:
    """Young's modulus and Poisson's ratio from the small-strain shear and bulk moduli."""
    return 9.0 * mu * kappa / (3.0 * kappa + mu), (3.0 * kappa - 2.0 * mu) / (2.0 * (3.0 * kappa + mu))


@dataclass(frozen=True)
class MaterialParams:
    """One hyperelastic model with concrete parameters: ``model`` name, E (Pa), ν and the model's extra parameters."""

    model: str
    E: float
    nu: float
    extra: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        model = canonical_model_name(self.model)
        object.__setattr__(self, "model", model)
        if not (self.E > 0.0):
            raise ValueError(f"E must be positive (Pa), got {self.E!r}")
        if not (-1.0 < self.nu < 0.5):
            raise ValueError(f"nu must lie in (-1, 0.5), got {self.nu!r}")
        allowed = _EXTRA_PARAMS[model]
        extra = {k: float(v) for k, v in self.extra.items()}
        unknown = sorted(set(extra) - set(allowed))
        if unknown:
            raise ValueError(f"model {model} has no parameter(s) {', '.join(unknown)}; allowed: {allowed or 'none'}")
        for name in allowed:
            extra.setdefault(name, 0.0)
        object.__setattr__(self, "extra", extra)
        c = self.coefficients()
        if model == "mooney_rivlin" and (c["c10"] < 0.0 or c["c01"] < 0.0):
            raise ValueError(
                f"Mooney-Rivlin needs 0 <= c01 <= mu/2 = {self.mu / 2:.6g} Pa so that c10 >= 0, got c01={c['c01']!r}"
            )

    @property
    def mu(self) -> float:
        """Small-strain shear modulus (Pa)."""
        return mu_kappa_from_E_nu(self.E, self.nu)[0]

    @property
    def kappa(self) -> float:
        """Small-strain bulk modulus (Pa)."""
        return mu_kappa_from_E_nu(self.E, self.nu)[1]

    def coefficients(self) -> dict[str, float]:
        """The energy coefficients (Pa) of the model: mu/kappa, c10/c01/kappa or c10/c20/c30/kappa."""
        mu, kappa = mu_kappa_from_E_nu(self.E, self.nu)
        if self.model == "neo_hookean":
            return {"mu": mu, "kappa": kappa}
        if self.model == "mooney_rivlin":
            c01 = self.extra["c01"]
            return {"c10": mu / 2.0 - c01, "c01": c01, "kappa": kappa}
        return {"c10": mu / 2.0, "c20": self.extra["c20"], "c30": self.extra["c30"], "kappa": kappa}

    def to_fem_material(self, density: float = 1070.0) -> Any:
        """The equivalent :class:`offline.fem.materials.Material` (imports the FEM package)."""
        from offline.fem import materials as fm

        c = self.coefficients()
        if self.model == "neo_hookean":
            return fm.neo_hookean(c["mu"], c["kappa"], density=density)
        if self.model == "mooney_rivlin":
            return fm.mooney_rivlin(c["c10"], c["c01"], c["kappa"], density=density)
        return fm.yeoh(c["c10"], c["c20"], c["c30"], c["kappa"], density=density)

    @classmethod
    def from_skin_material(cls, material: SkinMaterial) -> MaterialParams:
        """The fit-side form of a head's skin material (same names and parameters)."""
        return cls(material.model, material.E, material.nu, dict(material.shape))

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly description: model, E, nu, extras and the derived energy coefficients."""
        return {"model": self.model, "E": self.E, "nu": self.nu, **dict(self.extra),
                "coefficients": self.coefficients()}


def extra_param_names(model: str) -> tuple[str, ...]:
    """Names of a model's parameters beyond E and ν."""
    return _EXTRA_PARAMS[canonical_model_name(model)]
