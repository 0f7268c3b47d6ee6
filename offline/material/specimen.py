"""Standard test specimens: a tension strip (55 × 5 × 2 mm) and a compression cylinder (⌀50 × 12 mm).

A :class:`Specimen` knows its gauge length (the length whose nominal strain is reported) and its undeformed
cross-section (which turns nominal stress into axial force). ``auto`` picks the strip for tension (ε ≥ 0) and the
cylinder for compression (ε < 0), as a physical test lab would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SPECIMEN_CHOICES: tuple[str, ...] = ("strip", "cylinder", "auto")


@dataclass(frozen=True)
class Specimen:
    """A specimen: ``kind`` ("strip" or "cylinder") and its dimensions in metres.

    Strip: ``length`` along the pull axis x, ``width`` (y), ``thickness`` (z). Cylinder: ``length`` is the height
    along the axis z, ``width`` the diameter (``thickness`` equals it). ``area`` overrides the computed
    cross-section (real test files state it).
    """

    kind: str
    length: float
    width: float
    thickness: float
    area_override: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("strip", "cylinder"):
            raise ValueError(f"specimen kind must be 'strip' or 'cylinder', got {self.kind!r}")
        for name in ("length", "width", "thickness"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"specimen {name} must be a positive length in metres, got {value!r}")
        if self.area_override is not None and not (self.area_override > 0.0):
            raise ValueError(f"specimen cross-section must be positive (m²), got {self.area_override!r}")

    @property
    def area(self) -> float:
        """Undeformed cross-section (m²)."""
        if self.area_override is not None:
            return self.area_override
        if self.kind == "strip":
            return self.width * self.thickness
        return math.pi * self.width**2 / 4.0

    def describe(self) -> str:
        """Human-readable dimensions in millimetres."""
        if self.kind == "strip":
            return f"strip {self.length * 1e3:g} × {self.width * 1e3:g} × {self.thickness * 1e3:g} mm"
        return f"cylinder ⌀{self.width * 1e3:g} × {self.length * 1e3:g} mm"

    def as_dict(self) -> dict[str, float | str]:
        """JSON-friendly description (metres, m²)."""
        return {"kind": self.kind, "length_m": self.length, "width_m": self.width,
                "thickness_m": self.thickness, "area_m2": self.area}


def strip(length: float = 0.055, width: float = 0.005, thickness: float = 0.002) -> Specimen:
    """The tension strip (defaults 55 × 5 × 2 mm)."""
    return Specimen("strip", length, width, thickness)


def cylinder(diameter: float = 0.050, height: float = 0.012) -> Specimen:
    """The compression cylinder (defaults ⌀50 × 12 mm)."""
    return Specimen("cylinder", height, diameter, diameter)


def parse_dims_mm(text: str, count: int, what: str) -> tuple[float, ...]:
    """Parse ``"55x5x2"`` (millimetres) into metres; ``count`` numbers expected; ValueError naming ``what``."""
    parts = text.lower().replace("×", "x").split("x")
    try:
        values = tuple(float(p) * 1e-3 for p in parts)
    except ValueError:
        raise ValueError(f"{what}: expected {count} numbers in mm separated by 'x', got {text!r}") from None
    if len(values) != count or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"{what}: expected {count} positive numbers in mm separated by 'x', got {text!r}")
    return values


@dataclass(frozen=True)
class SpecimenPlan:
    """Which specimen tests which strains: ``tension`` for ε ≥ 0, ``compression`` for ε < 0."""

    tension: Specimen
    compression: Specimen

    def for_strains(self, strain: np.ndarray) -> list[tuple[Specimen, np.ndarray]]:
        """Split strains into (specimen, boolean mask) groups, skipping empty groups (order: compression, tension)."""
        eps = np.asarray(strain, dtype=float)
        groups = []
        if self.tension is self.compression or self.tension == self.compression:
            return [(self.tension, np.ones(eps.shape, dtype=bool))]
        neg = eps < 0.0
        if neg.any():
            groups.append((self.compression, neg))
        if (~neg).any():
            groups.append((self.tension, ~neg))
        return groups

    def area_per_point(self, strain: np.ndarray) -> np.ndarray:
        """Undeformed cross-section (m²) applying to each strain."""
        eps = np.asarray(strain, dtype=float)
        return np.where(eps < 0.0, self.compression.area, self.tension.area)

    def gauge_per_point(self, strain: np.ndarray) -> np.ndarray:
        """Gauge length (m) applying to each strain."""
        eps = np.asarray(strain, dtype=float)
        return np.where(eps < 0.0, self.compression.length, self.tension.length)

    def as_dict(self) -> dict[str, object]:
        """JSON-friendly description."""
        if self.tension == self.compression:
            return {"all": self.tension.as_dict()}
        return {"tension": self.tension.as_dict(), "compression": self.compression.as_dict()}


def make_plan(choice: str, strip_spec: Specimen | None = None, cylinder_spec: Specimen | None = None) -> SpecimenPlan:
    """Build the specimen plan for ``choice`` in strip|cylinder|auto (defaults: standard strip and cylinder)."""
    s = strip_spec or strip()
    c = cylinder_spec or cylinder()
    if choice == "strip":
        return SpecimenPlan(s, s)
    if choice == "cylinder":
        return SpecimenPlan(c, c)
    if choice == "auto":
        return SpecimenPlan(s, c)
    raise ValueError(f"specimen must be one of {', '.join(SPECIMEN_CHOICES)}, got {choice!r}")


@dataclass(frozen=True)
class PointPlan:
    """A specimen per sample, for joint fits of several files (e.g. a tension strip and a compression cylinder).

    Samples with ``index == k`` were tested on ``specimens[k]`` (named ``labels[k]``, usually the file). Offers the
    methods of :class:`SpecimenPlan` for the fitted strain array itself (same length as ``index``).
    """

    specimens: tuple[Specimen, ...]
    index: np.ndarray
    labels: tuple[str, ...]

    def _check(self, strain: np.ndarray) -> np.ndarray:
        eps = np.asarray(strain, dtype=float)
        if eps.shape != self.index.shape:
            raise ValueError(f"a joint specimen plan applies to its own {self.index.size} samples, got {eps.shape}")
        return eps

    def for_strains(self, strain: np.ndarray) -> list[tuple[Specimen, np.ndarray]]:
        self._check(strain)
        return [(self.specimens[k], self.index == k) for k in range(len(self.specimens)) if (self.index == k).any()]

    def area_per_point(self, strain: np.ndarray) -> np.ndarray:
        self._check(strain)
        return np.array([s.area for s in self.specimens])[self.index]

    def gauge_per_point(self, strain: np.ndarray) -> np.ndarray:
        self._check(strain)
        return np.array([s.length for s in self.specimens])[self.index]

    def single(self, k: int) -> SpecimenPlan:
        """The one-specimen plan of group ``k`` (for curves at other strains)."""
        return SpecimenPlan(self.specimens[k], self.specimens[k])

    def as_dict(self) -> dict[str, object]:
        return {label: {**s.as_dict(), "samples": int((self.index == k).sum())}
                for k, (label, s) in enumerate(zip(self.labels, self.specimens, strict=True))}
