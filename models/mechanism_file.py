"""A head's mechanism file (TOML): rigid bodies, joints, couplers and motors, checked at load into a `MechanismSpec`.

The mechanism is described at its neutral configuration (every motor at zero) in the head frame (metres, x to the
head's left, y up, z forward): each body's tracked frame and extent, each joint's anchor and axis, each coupler's
points and length. The file's tables are converted with msgspec (unknown keys refused), then the model is checked:
references exist, joints lie inside their bodies, motors sit on actuated joints, the rods close at neutral and no body
is left free when the motors are held. Every refusal is a :class:`~models.errors.SpecError` naming file, key and why.
The format is documented in ``docs/mechanism.md``; the kinematics live in :mod:`models.mechanism_kin`.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from models.errors import SpecError
from models.rigid import pose, rotvec_to_matrix

JOINT_KINDS = ("revolute", "prismatic", "spherical", "fixed")
COUPLER_KINDS = ("rod", "gear")
#: Joint kinds that carry one coordinate a motor can drive.
ONE_DOF = ("revolute", "prismatic")


class _Table(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A TOML table whose keys are all known."""


class MechanismTable(_Table, kw_only=True):
    """``[mechanism]``: the ground body and the closure tolerance at neutral."""

    name: str = ""
    ground: str
    closure_tolerance_m: float = 1e-6


class BodyTable(_Table, kw_only=True):
    """``[bodies.NAME]``: the body's frame at neutral, its extent, and the skin node set it carries (a link)."""

    origin: list[float]
    rotvec_deg: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    extent: float
    node_set: str | None = None


class JointTable(_Table, kw_only=True):
    """``[joints.NAME]``: a joint of ``child`` on ``parent``; ``tilt_deg_per_m`` makes a prismatic guide rock."""

    kind: str
    parent: str
    child: str
    anchor: list[float]
    axis: list[float] | None = None
    actuated: bool = False
    tilt_axis: list[float] | None = None
    tilt_deg_per_m: float = 0.0


class CouplerTable(_Table, kw_only=True):
    """``[couplers.NAME]``: a rod (a distance between two bodies' points) or a gear (angle ratio about an axis)."""

    kind: str
    a: str
    b: str
    a_point: list[float] | None = None
    b_point: list[float] | None = None
    length: float | None = None
    axis: list[float] | None = None
    ratio: float | None = None


class MotorTable(_Table, kw_only=True):
    """``[motors.NAME]``: an actuator driving an actuated joint; joint coordinate = ``ratio`` × motor value (SI)."""

    joint: str
    ratio: float = 1.0


class MechanismFile(_Table, kw_only=True):
    """The file's top level; each named table is converted on its own so errors name it."""

    mechanism: dict[str, Any]
    bodies: dict[str, dict[str, Any]]
    joints: dict[str, dict[str, Any]] = {}
    couplers: dict[str, dict[str, Any]] = {}
    motors: dict[str, dict[str, Any]] = {}


@dataclass(frozen=True)
class Tables:
    """The converted tables of a mechanism file (file units)."""

    mechanism: MechanismTable
    bodies: dict[str, BodyTable]
    joints: dict[str, JointTable]
    couplers: dict[str, CouplerTable]
    motors: dict[str, MotorTable]


def convert_table(raw: Any, cls: type, source: str, key: str) -> Any:
    """msgspec conversion of one TOML table; SpecError naming the table (and the key msgspec names inside it)."""
    try:
        return msgspec.convert(raw, cls, strict=False)
    except msgspec.ValidationError as exc:
        text = str(exc)
        inner = text.rsplit("at `$", 1)[-1].rstrip("`").lstrip(".") if "at `$" in text else ""
        unknown = re.search(r"unknown field `([^`]+)`", text)
        if unknown:
            inner = ".".join(k for k in (inner, unknown.group(1)) if k)
        full = ".".join(k for k in (key, inner) if k)
        raise SpecError(source, full or "(file)", text.split(" - at ")[0]) from None


def _tables(data: Mapping[str, Any], source: str) -> Tables:
    top = convert_table(dict(data), MechanismFile, source, "")
    return Tables(
        convert_table(top.mechanism, MechanismTable, source, "mechanism"),
        {n: convert_table(t, BodyTable, source, f"bodies.{n}") for n, t in top.bodies.items()},
        {n: convert_table(t, JointTable, source, f"joints.{n}") for n, t in top.joints.items()},
        {n: convert_table(t, CouplerTable, source, f"couplers.{n}") for n, t in top.couplers.items()},
        {n: convert_table(t, MotorTable, source, f"motors.{n}") for n, t in top.motors.items()},
    )


# ---------------------------------------------------------------------------- the checked model (SI)
@dataclass(frozen=True)
class Body:
    """A rigid body: its frame at neutral (``rest``, 4x4), the radius its joints must lie within, its node set."""

    name: str
    origin: np.ndarray
    rest: np.ndarray
    extent: float
    node_set: str | None = None


@dataclass(frozen=True)
class Joint:
    """A joint of ``child`` on ``parent`` at ``anchor`` (neutral, head frame); ``axis`` unit (revolute, prismatic)."""

    name: str
    kind: str
    parent: str
    child: str
    anchor: np.ndarray
    axis: np.ndarray | None = None
    actuated: bool = False
    tilt_axis: np.ndarray | None = None
    tilt_rate: float = 0.0  # rad of rocking per metre of travel (prismatic)


@dataclass(frozen=True)
class Coupler:
    """A rod (|a_point − b_point| = length, each point on its body) or a gear (angle_b = ratio × angle_a about axis)."""

    name: str
    kind: str
    a: str
    b: str
    a_point: np.ndarray | None = None
    b_point: np.ndarray | None = None
    length: float = 0.0
    axis: np.ndarray | None = None
    ratio: float = 1.0


@dataclass(frozen=True)
class Motor:
    """An actuator on an actuated joint; the joint coordinate is ``ratio`` × the motor value (rad or m)."""

    name: str
    joint: str
    ratio: float = 1.0


@dataclass(frozen=True)
class MechanismSpec:
    """A checked mechanism, SI, neutral configuration; ``source`` names the file in errors."""

    name: str
    ground: str
    bodies: dict[str, Body]
    joints: dict[str, Joint]
    couplers: dict[str, Coupler]
    motors: dict[str, Motor]
    source: str = "<mechanism>"
    tolerance: float = 1e-6
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def links(self) -> tuple[str, ...]:
        """The bodies that carry a skin node set (the attachment links), in file order."""
        return tuple(n for n, b in self.bodies.items() if b.node_set is not None)

    @property
    def motor_names(self) -> tuple[str, ...]:
        return tuple(self.motors)


# ---------------------------------------------------------------------------- loading
def read_mechanism(path: str | Path) -> MechanismSpec:
    """Read a mechanism file and check its structure (:func:`check_structure`); SpecError naming file and key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SpecError(str(path), "(file)", "mechanism file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(str(path), "(file)", f"not valid TOML: {exc}") from None
    return spec_from_dict(data, source=str(path))


def spec_from_dict(data: Mapping[str, Any], source: str = "<mechanism>") -> MechanismSpec:
    """Convert a parsed mechanism file and check its structure (:func:`check_structure`)."""
    if not isinstance(data, Mapping):
        raise SpecError(source, "(file)", "a mechanism file must be a TOML table")
    f = _tables(data, source)
    spec = _build(f, source)
    check_structure(spec)
    return spec


def _vec(v: list[float] | None, source: str, key: str, unit: bool = False) -> np.ndarray:
    if v is None:
        raise SpecError(source, key, "is required for this kind")
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise SpecError(source, key, "must be three finite numbers", v)
    if unit:
        n = float(np.linalg.norm(a))
        if n < 1e-12:
            raise SpecError(source, key, "an axis must not be zero", v)
        a = a / n
    return a


def _build(f: Tables, src: str) -> MechanismSpec:
    m = f.mechanism
    bodies: dict[str, Body] = {}
    for name, b in f.bodies.items():
        if not (b.extent > 0 and math.isfinite(b.extent)):
            raise SpecError(src, f"bodies.{name}.extent", "must be a positive length (m)", b.extent)
        o = _vec(b.origin, src, f"bodies.{name}.origin")
        rv = np.radians(_vec(b.rotvec_deg, src, f"bodies.{name}.rotvec_deg"))
        bodies[name] = Body(name, o, pose(rotvec_to_matrix(rv), o), float(b.extent), b.node_set)
    if m.ground not in bodies:
        raise SpecError(src, "mechanism.ground", f"names no body; bodies: {', '.join(bodies)}", m.ground)

    def body_ref(value: str, key: str) -> str:
        if value not in bodies:
            raise SpecError(src, key, f"names no body; bodies: {', '.join(bodies)}", value)
        return value

    joints: dict[str, Joint] = {}
    for name, j in f.joints.items():
        k = f"joints.{name}"
        if j.kind not in JOINT_KINDS:
            raise SpecError(src, f"{k}.kind", f"must be one of {', '.join(JOINT_KINDS)}", j.kind)
        parent, child = body_ref(j.parent, f"{k}.parent"), body_ref(j.child, f"{k}.child")
        if parent == child:
            raise SpecError(src, f"{k}.child", "a joint needs two different bodies", child)
        axis = _vec(j.axis, src, f"{k}.axis", unit=True) if j.kind in ONE_DOF else None
        tilt = None
        if j.tilt_deg_per_m:
            if j.kind != "prismatic":
                raise SpecError(src, f"{k}.tilt_deg_per_m", "only a prismatic guide can rock as it slides")
            tilt = _vec(j.tilt_axis, src, f"{k}.tilt_axis", unit=True)
        joints[name] = Joint(name, j.kind, parent, child, _vec(j.anchor, src, f"{k}.anchor"), axis, j.actuated, tilt,
                             math.radians(j.tilt_deg_per_m))
    couplers: dict[str, Coupler] = {}
    for name, c in f.couplers.items():
        k = f"couplers.{name}"
        if c.kind not in COUPLER_KINDS:
            raise SpecError(src, f"{k}.kind", f"must be one of {', '.join(COUPLER_KINDS)}", c.kind)
        a, b = body_ref(c.a, f"{k}.a"), body_ref(c.b, f"{k}.b")
        if c.kind == "rod":
            if c.length is None or not (c.length > 0 and math.isfinite(c.length)):
                raise SpecError(src, f"{k}.length", "a rod needs a positive length (m)", c.length)
            couplers[name] = Coupler(name, "rod", a, b, _vec(c.a_point, src, f"{k}.a_point"),
                                     _vec(c.b_point, src, f"{k}.b_point"), float(c.length))
        else:
            if c.ratio is None or not math.isfinite(c.ratio):
                raise SpecError(src, f"{k}.ratio", "a gear needs a finite ratio", c.ratio)
            couplers[name] = Coupler(name, "gear", a, b, axis=_vec(c.axis, src, f"{k}.axis", unit=True),
                                     ratio=float(c.ratio))
    motors: dict[str, Motor] = {}
    for name, mt in f.motors.items():
        if mt.joint not in joints:
            raise SpecError(src, f"motors.{name}.joint", f"names no joint; joints: {', '.join(joints)}", mt.joint)
        if not (math.isfinite(mt.ratio) and mt.ratio != 0):
            raise SpecError(src, f"motors.{name}.ratio", "must be finite and non-zero", mt.ratio)
        motors[name] = Motor(name, mt.joint, float(mt.ratio))
    tol = float(m.closure_tolerance_m)
    if not (tol > 0):
        raise SpecError(src, "mechanism.closure_tolerance_m", "must be positive", tol)
    return MechanismSpec(m.name, m.ground, bodies, joints, couplers, motors, src, tol)


# ---------------------------------------------------------------------------- checks
def check_structure(spec: MechanismSpec) -> None:
    """Refuse joints outside their bodies, motors on passive joints and rods that do not close at neutral
    (SpecError naming the key). Bodies left free with every motor held need the kinematics:
    :func:`models.mechanism_kin.check_constrained`."""
    src = spec.source
    for name, j in spec.joints.items():
        for side in ("parent", "child"):
            body = spec.bodies[getattr(j, side)]
            d = float(np.linalg.norm(j.anchor - body.origin))
            if d > body.extent:
                raise SpecError(src, f"joints.{name}.anchor", f"lies {d * 1e3:.1f} mm from the origin of its {side} "
                                f"{body.name!r}, beyond its extent {body.extent * 1e3:.1f} mm (a joint outside its "
                                "body)", j.anchor.tolist())
    for name, c in spec.couplers.items():
        if c.kind != "rod":
            continue
        for side in ("a", "b"):
            body = spec.bodies[getattr(c, side)]
            p = getattr(c, f"{side}_point")
            d = float(np.linalg.norm(p - body.origin))
            if d > body.extent:
                raise SpecError(src, f"couplers.{name}.{side}_point", f"lies {d * 1e3:.1f} mm from the origin of "
                                f"{body.name!r}, beyond its extent {body.extent * 1e3:.1f} mm", p.tolist())
    driven: dict[str, str] = {}
    for name, mt in spec.motors.items():
        j = spec.joints[mt.joint]
        if not j.actuated or j.kind not in ONE_DOF:
            why = "is passive (actuated = false)" if j.kind in ONE_DOF else f"is {j.kind}, not revolute or prismatic"
            raise SpecError(src, f"motors.{name}.joint", f"joint {j.name!r} {why}: a motor drives only an actuated "
                            "revolute or prismatic joint", mt.joint)
        if mt.joint in driven:
            raise SpecError(src, f"motors.{name}.joint", f"joint {mt.joint!r} is driven by motor "
                            f"{driven[mt.joint]!r} already", mt.joint)
        driven[mt.joint] = name
    for name, j in spec.joints.items():
        if j.actuated and name not in driven:
            raise SpecError(src, f"joints.{name}.actuated", "an actuated joint needs a motor ([motors.NAME] joint = "
                            f"{name!r})", True)
    for name, c in spec.couplers.items():
        if c.kind == "rod":
            gap = float(np.linalg.norm(c.a_point - c.b_point)) - c.length
            if abs(gap) > spec.tolerance:
                raise SpecError(src, f"couplers.{name}.length", f"the mechanism does not close at neutral: the rod's "
                                f"points are {np.linalg.norm(c.a_point - c.b_point) * 1e3:.4f} mm apart, its length "
                                f"is {c.length * 1e3:.4f} mm (gap {gap * 1e3:+.4f} mm)", c.length)


# ---------------------------------------------------------------------------- design parameters
def get_param(spec: MechanismSpec, name: str) -> float:
    """A scalar design parameter by name: ``joints.J.anchor[i]``, ``couplers.C.length``, ``couplers.C.a_point[i]``,
    ``couplers.C.b_point[i]``, ``couplers.C.ratio``, ``motors.M.ratio``."""
    table, item, attr, idx = _parse_param(name)
    value = getattr(getattr(spec, table)[item], attr)
    return float(value if idx is None else value[idx])


def with_params(spec: MechanismSpec, values: Mapping[str, float]) -> MechanismSpec:
    """A copy of ``spec`` with these design parameters set (see :func:`get_param` for the names)."""
    tables = {"joints": dict(spec.joints), "couplers": dict(spec.couplers), "motors": dict(spec.motors)}
    for name, value in values.items():
        table, item, attr, idx = _parse_param(name)
        obj = tables[table][item]
        if idx is None:
            new: Any = float(value)
        else:
            new = np.array(getattr(obj, attr), dtype=float)
            new[idx] = float(value)
        tables[table][item] = replace(obj, **{attr: new})
    return replace(spec, joints=tables["joints"], couplers=tables["couplers"], motors=tables["motors"])


def _parse_param(name: str) -> tuple[str, str, str, int | None]:
    parts = name.split(".")
    if len(parts) != 3 or parts[0] not in ("joints", "couplers", "motors"):
        raise KeyError(f"not a design parameter: {name!r}")
    table, item, attr = parts
    idx = None
    if attr.endswith("]"):
        attr, _, i = attr[:-1].partition("[")
        idx = int(i)
    return table, item, attr, idx
