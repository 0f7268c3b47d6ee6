"""The mechanical envelope of a link-layout design, and the design variables it allows.

An envelope file (TOML, ``--envelope FILE``) bounds how far the layout design may change a head's mechanism. Every
key is optional; the defaults are those of ``DEFAULTS``::

    [envelope]
    joint_move_mm = 15.0      # a joint's anchor or a rod's end moves at most this far (a ball around the design)
    axis_tilt_deg = 20.0      # a revolute or prismatic axis tilts at most this much
    rod_length_rel = 0.20     # a rod's length within ±20 % of the design's
    ratio_rel = 0.20          # a belt (motor ratio) or gear ratio within ±20 %
    attachment_rings = 0      # whole rings of surface triangles an attachment node set may grow or shrink by

    [attachments.lower_lip]   # per attachment node set: its own ring limit
    rings = 2
    [joints.jaw_hinge]        # per item: fixed = true, or its own limit
    move_mm = 25.0
    [couplers.jaw_rod]
    length_rel = 0.1
    [motors.jaw]
    fixed = true

The design variables are offsets θ from the mechanism's design values: a joint anchor's or rod end's displacement
(m, three per point, one ball), an axis's tilt (rad, two per axis: the rotation vector ω ⟂ n turning n, one ball),
a rod's length (m, a box), a gear or belt ratio (a box). The motors' limits and speeds are the head config's and do
not change. Attachment rings are no continuous variables: the discrete ring step of the layout job
(:mod:`offline.design.mechanism_design_rings`) changes the node sets within ``ring_limits``.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from models.errors import SpecError
from models.mechanism_file import MechanismSpec, convert_table, get_param, with_params
from models.rigid import rotvec_to_matrix

DEFAULTS = {"joint_move_mm": 15.0, "axis_tilt_deg": 20.0, "rod_length_rel": 0.20, "ratio_rel": 0.20,
            "attachment_rings": 0}


class _Table(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    pass


class EnvelopeTable(_Table, kw_only=True):
    """The ``[envelope]`` table: the limits every item gets unless it names its own."""

    joint_move_mm: float = DEFAULTS["joint_move_mm"]
    axis_tilt_deg: float = DEFAULTS["axis_tilt_deg"]
    rod_length_rel: float = DEFAULTS["rod_length_rel"]
    ratio_rel: float = DEFAULTS["ratio_rel"]
    attachment_rings: int = DEFAULTS["attachment_rings"]


class ItemTable(_Table, kw_only=True):
    """One joint's, coupler's or motor's own limits (``fixed``: the layout design leaves it as it is)."""

    fixed: bool = False
    move_mm: float | None = None
    tilt_deg: float | None = None
    length_rel: float | None = None
    ratio_rel: float | None = None


class AttachmentTable(_Table, kw_only=True):
    """One attachment node set's own ring limit."""

    rings: int


class EnvelopeFile(_Table, kw_only=True):
    envelope: EnvelopeTable = msgspec.field(default_factory=EnvelopeTable)
    attachments: dict[str, Any] = msgspec.field(default_factory=dict)
    joints: dict[str, Any] = msgspec.field(default_factory=dict)
    couplers: dict[str, Any] = msgspec.field(default_factory=dict)
    motors: dict[str, Any] = msgspec.field(default_factory=dict)


@dataclass(frozen=True)
class Envelope:
    """The checked envelope: defaults and per-item limits (SI: m, rad, relative fractions)."""

    joint_move: float = DEFAULTS["joint_move_mm"] * 1e-3
    axis_tilt: float = math.radians(DEFAULTS["axis_tilt_deg"])
    rod_length_rel: float = DEFAULTS["rod_length_rel"]
    ratio_rel: float = DEFAULTS["ratio_rel"]
    items: dict[str, ItemTable] = field(default_factory=dict)  # "joints.NAME" → its table
    source: str = "(default envelope)"
    attachment_rings: int = 0  # whole rings either way, every attachment node set
    attachments: dict[str, int] = field(default_factory=dict)  # node set → its own ring limit

    def ring_limits(self, node_sets: list[str] | tuple[str, ...]) -> dict[str, int]:
        """Each attachment node set's ring limit (its own, else the envelope's)."""
        return {n: int(self.attachments.get(n, self.attachment_rings)) for n in node_sets}

    def limit(self, item: str, what: str) -> float:
        """The limit ``what`` (move, tilt, length_rel, ratio_rel) of ``item`` ("joints.J", ...); 0 when fixed."""
        t = self.items.get(item)
        if t is not None and t.fixed:
            return 0.0
        own = {"move": "move_mm", "tilt": "tilt_deg", "length_rel": "length_rel", "ratio_rel": "ratio_rel"}[what]
        value = getattr(t, own) if t is not None else None
        if value is not None:
            return value * 1e-3 if what == "move" else math.radians(value) if what == "tilt" else float(value)
        return {"move": self.joint_move, "tilt": self.axis_tilt, "length_rel": self.rod_length_rel,
                "ratio_rel": self.ratio_rel}[what]

    def to_json(self) -> dict[str, Any]:
        """The envelope for the report (mm, degrees)."""
        return {"source": self.source, "joint_move_mm": self.joint_move * 1e3,
                "axis_tilt_deg": math.degrees(self.axis_tilt), "rod_length_rel": self.rod_length_rel,
                "ratio_rel": self.ratio_rel, "attachment_rings": self.attachment_rings,
                "attachments": dict(self.attachments),
                "items": {k: msgspec.to_builtins(v) for k, v in self.items.items()}}

    def continuous_json(self) -> dict[str, Any]:
        """The limits of the continuous design variables only (what a checkpoint's design depends on)."""
        return {k: v for k, v in self.to_json().items() if k not in CONTINUOUS_IGNORED}


#: Envelope entries that do not change the continuous design (a design made under one envelope resumes under another
#: that differs only in these).
CONTINUOUS_IGNORED = ("source", "attachment_rings", "attachments")


def _rings(value: Any, source: str, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise SpecError(source, key, "must be a whole number of rings >= 0", value)
    return int(value)


def _nonneg(value: float | None, source: str, key: str) -> None:
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise SpecError(source, key, "must be a finite number >= 0", value)


def envelope_from_dict(data: Mapping[str, Any], spec: MechanismSpec, source: str = "<envelope>") -> Envelope:
    """Check a parsed envelope against the mechanism ``spec``; SpecError naming the file, key and why."""
    f = convert_table(dict(data), EnvelopeFile, source, "")
    e = f.envelope
    for k in ("joint_move_mm", "axis_tilt_deg", "rod_length_rel", "ratio_rel"):
        _nonneg(getattr(e, k), source, f"envelope.{k}")
    if e.rod_length_rel >= 1 or e.ratio_rel >= 1:
        raise SpecError(source, "envelope.rod_length_rel", "relative limits must be below 1 (a rod or ratio cannot "
                        "reach zero)", max(e.rod_length_rel, e.ratio_rel))
    if e.axis_tilt_deg > 90:
        raise SpecError(source, "envelope.axis_tilt_deg", "must be at most 90 degrees", e.axis_tilt_deg)
    rings = _rings(data.get("envelope", {}).get("attachment_rings", 0), source, "envelope.attachment_rings")
    node_sets = [b.node_set for b in spec.bodies.values() if b.node_set is not None]
    attachments: dict[str, int] = {}
    for name, raw in f.attachments.items():
        if not isinstance(raw, Mapping) or set(raw) - {"rings"}:
            raise SpecError(source, f"attachments.{name}", "must be a table with the one key rings")
        if name not in node_sets:
            raise SpecError(source, f"attachments.{name}", f"names no attachment node set of mechanism "
                            f"{spec.name!r}; known: {', '.join(node_sets)}")
        attachments[name] = _rings(raw.get("rings"), source, f"attachments.{name}.rings")
    items: dict[str, ItemTable] = {}
    known = {"joints": spec.joints, "couplers": spec.couplers, "motors": spec.motors}
    for table, rows in (("joints", f.joints), ("couplers", f.couplers), ("motors", f.motors)):
        for name, raw in rows.items():
            t = convert_table(raw, ItemTable, source, f"{table}.{name}")
            if name not in known[table]:
                raise SpecError(source, f"{table}.{name}", f"names no {table[:-1]} of mechanism {spec.name!r}; "
                                f"known: {', '.join(known[table])}")
            for k in ("move_mm", "tilt_deg", "length_rel", "ratio_rel"):
                _nonneg(getattr(t, k), source, f"{table}.{name}.{k}")
            items[f"{table}.{name}"] = t
    return Envelope(e.joint_move_mm * 1e-3, math.radians(e.axis_tilt_deg), e.rod_length_rel, e.ratio_rel, items,
                    source, rings, attachments)


def load_envelope(path: str | Path | None, spec: MechanismSpec) -> Envelope:
    """The envelope of a file (None: the defaults); SpecError naming the file, key and why."""
    if path is None:
        return Envelope()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SpecError(str(path), "(file)", "envelope file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(str(path), "(file)", f"not valid TOML: {exc}") from None
    return envelope_from_dict(data, spec, str(path))


# ------------------------------------------------------------------------------------------------ design variables
@dataclass(frozen=True)
class VariableGroup:
    """Design variables bounded together: ``kind`` ball (a point's move, an axis's tilt: ‖θ_g‖ ≤ radius) or box
    (lo ≤ θ ≤ hi); ``item`` the joint/coupler/motor and ``what`` (anchor, a_point, b_point, axis, length, ratio)."""

    item: str
    what: str
    index: tuple[int, ...]
    kind: str
    radius: float = 0.0
    lo: float = 0.0
    hi: float = 0.0
    unit: str = "mm"


@dataclass(frozen=True)
class DesignSpace:
    """The design variables θ of a mechanism within an envelope: names, scales and bound groups."""

    spec: MechanismSpec
    names: tuple[str, ...]
    scale: np.ndarray  # a typical size of each variable (m, rad, ratio): conditioning and regularization
    groups: tuple[VariableGroup, ...]
    envelope: Envelope

    @property
    def size(self) -> int:
        return len(self.names)

    def project(self, theta: np.ndarray) -> np.ndarray:
        """θ moved into every group's ball or box."""
        t = np.array(theta, dtype=np.float64)
        for g in self.groups:
            i = list(g.index)
            if g.kind == "ball":
                n = float(np.linalg.norm(t[i]))
                if n > g.radius:
                    t[i] *= g.radius / n if n > 0 else 0.0
            else:
                t[i] = np.clip(t[i], g.lo, g.hi)
        return t

    def touching(self, bodies: Iterable[str]) -> np.ndarray:
        """Mask of the variables of the joints, couplers and motors acting on any of ``bodies`` (the design of one
        linkage loop, when an :class:`~models.mechanism_kin.AssemblyError` names its bodies)."""
        bodies = set(bodies)
        spec = self.spec
        mask = np.zeros(self.size, dtype=bool)
        for g in self.groups:
            kind, name = g.item.split(".", 1)
            if kind == "joints":
                j = spec.joints[name]
                hit = j.parent in bodies or j.child in bodies
            elif kind == "couplers":
                c = spec.couplers[name]
                hit = c.a in bodies or c.b in bodies
            elif kind == "motors":
                j = spec.joints[spec.motors[name].joint]
                hit = j.parent in bodies or j.child in bodies
            else:
                hit = False
            if hit:
                mask[list(g.index)] = True
        return mask

    def active(self, theta: np.ndarray, tol: float = 1e-3) -> list[VariableGroup]:
        """The groups at their bound (within ``tol`` of it, relative)."""
        out = []
        for g in self.groups:
            v = np.asarray(theta)[list(g.index)]
            if g.kind == "ball":
                if g.radius > 0 and np.linalg.norm(v) >= g.radius * (1 - tol):
                    out.append(g)
            elif g.hi > g.lo and (v[0] <= g.lo + tol * (g.hi - g.lo) or v[0] >= g.hi - tol * (g.hi - g.lo)):
                out.append(g)
        return out

    def params(self, theta: np.ndarray) -> dict[str, float]:
        """The mechanism's named parameter values (``models.mechanism_file.with_params``) at θ."""
        theta = np.asarray(theta, dtype=np.float64)
        values: dict[str, float] = {}
        for g in self.groups:
            v = theta[list(g.index)]
            if g.what == "axis":
                j = self.spec.joints[g.item.split(".", 1)[1]]
                axis = tilted_axis(j.axis, v)
                for i in range(3):
                    values[f"{g.item}.axis[{i}]"] = float(axis[i])
            elif g.kind == "ball":
                base = getattr(self._obj(g.item), g.what)
                for i in range(3):
                    values[f"{g.item}.{g.what}[{i}]"] = float(base[i] + v[i])
            else:
                values[f"{g.item}.{g.what}"] = get_param(self.spec, f"{g.item}.{g.what}") + float(v[0])
        return values

    def apply(self, theta: np.ndarray) -> MechanismSpec:
        """The mechanism with design θ (its rods no longer close at the old neutral: it is re-assembled at load)."""
        return with_params(self.spec, self.params(theta))

    def _obj(self, item: str) -> Any:
        table, name = item.split(".", 1)
        return getattr(self.spec, table)[name]


def tilted_axis(n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The unit axis ``n`` turned by the rotation vector ω = w₀ e₁ + w₁ e₂ (e₁, e₂ ⟂ n): a tilt of ‖w‖ rad."""
    e1, e2 = axis_basis(n)
    return rotvec_to_matrix(w[0] * e1 + w[1] * e2) @ n


def axis_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``n`` and to each other."""
    ref = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def design_space(spec: MechanismSpec, envelope: Envelope) -> DesignSpace:
    """Every design variable the envelope allows on ``spec``: joint anchors (ball), revolute/prismatic axes (tilt
    ball), rod ends (ball) and lengths (box), gear and motor ratios (box). Items whose limit is 0 are left out."""
    names: list[str] = []
    scale: list[float] = []
    groups: list[VariableGroup] = []

    def add(item: str, what: str, n: int, kind: str, s: float, unit: str, **bounds: float) -> None:
        idx = tuple(range(len(names), len(names) + n))
        labels = [f"{item}.{what}[{i}]" for i in range(n)] if n > 1 else [f"{item}.{what}"]
        if what == "axis":
            labels = [f"{item}.axis_tilt[{i}]" for i in range(n)]
        names.extend(labels)
        scale.extend([s] * n)
        groups.append(VariableGroup(item, what, idx, kind, unit=unit, **bounds))

    for name, j in spec.joints.items():
        item = f"joints.{name}"
        move = envelope.limit(item, "move")
        if move > 0:
            add(item, "anchor", 3, "ball", 5e-3, "mm", radius=move)
        tilt = envelope.limit(item, "tilt")
        if tilt > 0 and j.axis is not None:
            add(item, "axis", 2, "ball", math.radians(5.0), "deg", radius=tilt)
    for name, c in spec.couplers.items():
        item = f"couplers.{name}"
        if c.kind == "rod":
            move = envelope.limit(item, "move")
            if move > 0:
                add(item, "a_point", 3, "ball", 5e-3, "mm", radius=move)
                add(item, "b_point", 3, "ball", 5e-3, "mm", radius=move)
            rel = envelope.limit(item, "length_rel")
            if rel > 0:
                add(item, "length", 1, "box", 0.05 * c.length, "mm", lo=-rel * c.length, hi=rel * c.length)
        else:
            rel = envelope.limit(item, "ratio_rel")
            if rel > 0:
                r = abs(c.ratio)
                add(item, "ratio", 1, "box", 0.05 * r, "ratio", lo=-rel * r, hi=rel * r)
    for name, m in spec.motors.items():
        item = f"motors.{name}"
        rel = envelope.limit(item, "ratio_rel")
        if rel > 0:
            r = abs(m.ratio)
            add(item, "ratio", 1, "box", 0.05 * r, "ratio", lo=-rel * r, hi=rel * r)
    return DesignSpace(spec, tuple(names), np.array(scale), tuple(groups), envelope)
