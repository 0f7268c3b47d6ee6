"""The skin material vocabulary shared by the head config, material fitting and the FEM, and its config forms.

One set of model names (``neo_hookean``, ``mooney_rivlin``, ``yeoh``) and one parameterisation: the small-strain
Young's modulus E (Pa) and Poisson's ratio ν, plus each model's shape parameters (Mooney-Rivlin ``c01``; Yeoh
``c20``, ``c30``; Pa). A head names its skin material in a ``[skin_material]`` table, either inline::

    [skin_material]
    model = "neo_hookean"
    E = 45561.0          # Pa
    nu = 0.47
    note = "why this material"

or by a ``likeness offline fit-material --out`` result file (``fit = "material_fit.json"``, relative to the head
file), optionally overriding ``nu`` when the fit's data do not identify it. Pure Python: no offline imports.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from models.errors import SpecError

MATERIAL_MODELS: tuple[str, ...] = ("neo_hookean", "mooney_rivlin", "yeoh")
#: Parameters of each model beyond E and ν (Pa).
SHAPE_PARAMS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "neo_hookean": (), "mooney_rivlin": ("c01",), "yeoh": ("c20", "c30"),
})
_ALIASES = {"neohookean": "neo_hookean", "neo_hooke": "neo_hookean", "neohooke": "neo_hookean",
            "mooneyrivlin": "mooney_rivlin", "mr": "mooney_rivlin"}
MATERIAL_FIT_FORMAT = "likeness-material-fit"
DEFAULT_DENSITY = 1070.0  # kg/m³, platinum-cure silicone


def canonical_material_model(name: str) -> str:
    """The canonical model name for ``name`` (case-insensitive; ``-`` and ``_`` alike; a few aliases)."""
    key = str(name).strip().lower().replace("-", "_")
    key = _ALIASES.get(key, key)
    if key not in MATERIAL_MODELS:
        raise ValueError(f"unknown material model {name!r}; choose one of {', '.join(MATERIAL_MODELS)}")
    return key


@dataclass(frozen=True)
class SkinMaterial:
    """A skin material: model, E (Pa), ν, shape parameters (Pa), density (kg/m³), where it came from and why."""

    model: str
    E: float
    nu: float
    shape: Mapping[str, float] = field(default_factory=dict)
    density: float = DEFAULT_DENSITY
    source: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        model = canonical_material_model(self.model)
        object.__setattr__(self, "model", model)
        if not (isinstance(self.E, int | float) and math.isfinite(self.E) and self.E > 0):
            raise ValueError(f"E must be a positive number of pascals, got {self.E!r}")
        if not (isinstance(self.nu, int | float) and -1.0 < self.nu < 0.5):
            raise ValueError(f"nu must lie in (-1, 0.5), got {self.nu!r}")
        if not (math.isfinite(self.density) and self.density > 0):
            raise ValueError(f"density must be positive (kg/m³), got {self.density!r}")
        shape = {str(k): float(v) for k, v in dict(self.shape).items()}
        unknown = sorted(set(shape) - set(SHAPE_PARAMS[model]))
        if unknown:
            raise ValueError(f"model {model} has no parameter(s) {', '.join(unknown)}; "
                             f"allowed: {', '.join(SHAPE_PARAMS[model]) or 'none beyond E and nu'}")
        for name in SHAPE_PARAMS[model]:
            shape.setdefault(name, 0.0)
        object.__setattr__(self, "shape", MappingProxyType(shape))

    def as_dict(self) -> dict[str, Any]:
        return {"model": self.model, "E": self.E, "nu": self.nu, **dict(self.shape), "density": self.density,
                "source": self.source, **({"note": self.note} if self.note else {})}


def material_from_fit_file(path: str | Path, nu: float | None = None) -> SkinMaterial:
    """The material in a ``fit-material --out`` file; ``nu`` replaces the fitted ν (for data that do not pin it)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise SpecError(str(path), "file", f"cannot read material fit: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise SpecError(str(path), "json", f"not valid JSON: {exc}") from exc
    if doc.get("format") != MATERIAL_FIT_FORMAT:
        raise SpecError(str(path), "format", f"expected {MATERIAL_FIT_FORMAT!r} (a fit-material --out file)",
                        doc.get("format"))
    try:
        model = canonical_material_model(doc["model"])
        shape = {k: doc["params"][k] for k in SHAPE_PARAMS[model]}
        source = f"fit {path.name}: {', '.join(doc.get('measurements_files', [doc.get('measurements', '?')]))}"
        if nu is not None:
            source += f"; nu set to {nu:g} in the head config (the fit reports whether its data identify nu)"
        return SkinMaterial(model, float(doc["E_Pa"]), float(doc["nu"] if nu is None else nu), shape,
                            source=source)
    except KeyError as exc:
        raise SpecError(str(path), str(exc.args[0]), "missing from the material fit") from exc
    except (TypeError, ValueError) as exc:
        raise SpecError(str(path), "params", str(exc)) from exc


_TABLE_KEYS = {"model", "E", "nu", "c01", "c20", "c30", "density", "fit", "note"}


def check_material_table(table: Mapping[str, Any], source: str | Path, key: str = "skin_material") -> None:
    """Check a ``[skin_material]`` table without reading any file (heads load fast and anywhere; the fit file is
    read by :func:`material_from_table` when the material is needed)."""
    if "fit" in table:
        _check_common(table, str(source), key)
    else:
        material_from_table(table, source, key)


def _check_common(table: Mapping[str, Any], src: str, key: str) -> str:
    """Keys, number types and the note; returns the note."""
    unknown = sorted(set(table) - _TABLE_KEYS)
    if unknown:
        raise SpecError(src, f"{key}.{unknown[0]}", f"unknown key; allowed: {', '.join(sorted(_TABLE_KEYS))}")
    for name in ("E", "nu", "c01", "c20", "c30", "density"):
        if name in table and (isinstance(table[name], bool) or not isinstance(table[name], int | float)):
            raise SpecError(src, f"{key}.{name}", "must be a number (SI: Pa, kg/m³)", table[name])
    note = table.get("note", "")
    if not isinstance(note, str):
        raise SpecError(src, f"{key}.note", "must be a string", note)
    if "fit" in table:
        if not isinstance(table["fit"], str) or not table["fit"]:
            raise SpecError(src, f"{key}.fit", "must be a path to a fit-material result file", table["fit"])
        clash = sorted(set(table) & {"model", "E", "c01", "c20", "c30"})
        if clash:
            raise SpecError(src, f"{key}.{clash[0]}", "give either fit = FILE or inline parameters, not both")
    return note


def material_from_table(table: Mapping[str, Any], source: str | Path, key: str = "skin_material") -> SkinMaterial:
    """The material of a ``[skin_material]`` table of the head file ``source`` (a fit file resolves beside it)."""
    src = str(source)
    note = _check_common(table, src, key)
    if "fit" in table:
        path = Path(table["fit"])
        path = path if path.is_absolute() else Path(src).parent / path
        mat = material_from_fit_file(path, table.get("nu"))
        return SkinMaterial(mat.model, mat.E, mat.nu, mat.shape, float(table.get("density", DEFAULT_DENSITY)),
                            source=f"{key}.fit in {Path(src).name} → {mat.source}", note=note)
    for name in ("model", "E", "nu"):
        if name not in table:
            raise SpecError(src, f"{key}.{name}", "required (or fit = FILE)")
    try:
        model = canonical_material_model(table["model"])
        shape = {n: table[n] for n in SHAPE_PARAMS[model] if n in table}
        extra = sorted(set(table) & {"c01", "c20", "c30"} - set(shape))
        if extra:
            raise ValueError(f"model {model} has no parameter {extra[0]}")
        return SkinMaterial(model, float(table["E"]), float(table["nu"]), shape,
                            float(table.get("density", DEFAULT_DENSITY)),
                            source=f"inline [{key}] in {Path(src).name}", note=note)
    except ValueError as exc:
        raise SpecError(src, key, str(exc)) from exc
