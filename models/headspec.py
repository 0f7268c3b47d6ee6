"""Head specification (TOML): actuators, buses, groups, links and the paths of learned models.

Configs use operator units (degrees for rotary actuators, millimetres for linear ones); the loaded
:class:`HeadSpec` is in SI (radians, metres, seconds). Every validation error names the file, the
key and the bad value. The file's keys, value types and defaults are declared once, in :mod:`models.headschema`;
this module checks the values of those typed tables and builds the SI spec types from them.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import msgspec

from models.errors import SpecError
from models.headschema import (
    ActuatorTable,
    BusTable,
    GroupTable,
    HeartbeatTable,
    LinkTable,
    PathsTable,
    check_head_file,
)
from models.jsonfile import read_text
from models.material import SkinMaterial, check_material_table, material_from_table

#: Config unit → (kind, factor to SI, SI unit name).
UNITS: dict[str, tuple[Literal["rotary", "linear"], float, str]] = {
    "deg": ("rotary", math.pi / 180.0, "rad"),
    "rad": ("rotary", 1.0, "rad"),
    "mm": ("linear", 1e-3, "m"),
    "m": ("linear", 1.0, "m"),
}
GROUP_KINDS = ("together", "mirror", "coupled")


@dataclass(frozen=True)
class ActuatorSpec:
    """One actuator, in SI, from an ``[[actuators]]`` table (:class:`models.headschema.ActuatorTable`; its ``id`` is
    ``device_id`` here). ``unit`` is the config unit the operator sees (deg or mm); ``kind`` follows from it."""

    name: str
    bus: str
    device_id: int
    unit: str
    kind: Literal["rotary", "linear"]
    min: float
    max: float
    neutral: float
    max_velocity: float
    max_acceleration: float
    counts_per_rev: int
    gear_ratio: float
    direction: int
    zero_count: int
    options: Mapping[str, Any]
    #: |commanded − measured| (SI) the actuator may exceed for ``following_error_time_s`` before the head faults;
    #: None: the core's default (:mod:`runtime.core.watch`)
    max_following_error: float | None = None
    following_error_time_s: float | None = None

    @property
    def unit_scale(self) -> float:
        """Multiply a config-unit value by this to get SI."""
        return UNITS[self.unit][1]

    def to_config_units(self, value: float) -> float:
        return value / self.unit_scale

    def from_config_units(self, value: float) -> float:
        return value * self.unit_scale


@dataclass(frozen=True)
class BusSpec:
    """A motor bus: backend name, backend options, and whether to emulate it in-process."""

    name: str
    driver: str
    options: Mapping[str, Any]
    simulated: bool
    heartbeat: HeartbeatSpec | None
    #: age (s) of the devices' newest feedback past which the core publishes ``feedback_late``; None: its default
    feedback_timeout_s: float | None = None
    #: age (s) past which the head faults naming the bus; None: the core's default (``[safety] feedback_timeout_s``)
    feedback_fault_s: float | None = None

    def driver_options(self) -> dict[str, Any]:
        """The options handed to the driver: ``options``, with the heartbeat as ``heartbeat_period_s`` and
        ``heartbeat_timeout_s`` when ``[buses.NAME.heartbeat]`` sets it."""
        out = dict(self.options)
        if self.heartbeat is not None:
            out.update(heartbeat_period_s=self.heartbeat.period_s, heartbeat_timeout_s=self.heartbeat.timeout_s)
        return out


#: Consumer heartbeat timeout when the config names only the producer period, in periods.
HEARTBEAT_TIMEOUT_PERIODS = 2.0


@dataclass(frozen=True)
class HeartbeatSpec:
    """A bus's device heartbeat: producer period and consumer timeout (s); loss is seen within ``timeout_s``."""

    period_s: float
    timeout_s: float


@dataclass(frozen=True)
class GroupSpec:
    """Actuators that move together (equal), mirror (gains, default +1/-1) or are coupled (max spread)."""

    name: str
    kind: Literal["together", "mirror", "coupled"]
    actuators: tuple[str, ...]
    gains: tuple[float, ...]
    max_spread: float | None  # SI; only for "coupled"


@dataclass(frozen=True)
class LinkSpec:
    """An attachment link of the skin, moved by ``actuators`` (none for rigid skull links)."""

    name: str
    actuators: tuple[str, ...]
    node_set: str
    rigid: bool


@dataclass(frozen=True)
class HeadSpec:
    """A validated head, in SI; ``source`` is the file it came from (paths resolve beside it)."""

    name: str
    source: Path
    actuators: tuple[ActuatorSpec, ...]
    buses: Mapping[str, BusSpec]
    groups: tuple[GroupSpec, ...]
    links: tuple[LinkSpec, ...]
    paths: Mapping[str, Path]
    description: str
    #: Raw tables owned by other layers (``runtime``, ``safety``, ``api``, ``inputs``, ``skin``), validated there.
    sections: Mapping[str, Mapping[str, Any]]
    #: The ``[skin_material]`` table (checked; a fit file it names is read by :meth:`skin_material`).
    skin_material_table: Mapping[str, Any] | None
    #: ``[paths] predictor_optional``: run without the predictor's target channels when its file is missing.
    predictor_optional: bool

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.actuators)

    @property
    def neutral_pose(self) -> tuple[float, ...]:
        """Every actuator's neutral value (SI), in actuator order: the pose at which the skin is at rest."""
        return tuple(a.neutral for a in self.actuators)

    def actuator(self, name: str) -> ActuatorSpec:
        for a in self.actuators:
            if a.name == name:
                return a
        raise KeyError(name)

    def actuators_on(self, bus: str) -> tuple[ActuatorSpec, ...]:
        return tuple(a for a in self.actuators if a.bus == bus)

    def path(self, key: str) -> Path | None:
        """Absolute path of a referenced file (``predictor``, ``linkmap``, ...), or None if not set."""
        return self.paths.get(key)

    def section(self, key: str) -> Mapping[str, Any]:
        return self.sections.get(key, {})

    def skin_material(self) -> SkinMaterial | None:
        """The skin material (inline, or read now from the fit-material file named); None when not given."""
        if self.skin_material_table is None:
            return None
        return material_from_table(self.skin_material_table, self.source)


# ---------------------------------------------------------------------------- loading
def load_head(path: str | Path) -> HeadSpec:
    """Load and validate a head spec TOML file."""
    path = Path(path)
    text = read_text(path, "head spec")  # SpecError when unreadable or not UTF-8
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(str(path), "toml", f"not valid TOML: {exc}") from None
    except RecursionError:
        raise SpecError(str(path), "toml", "arrays or tables nested too deeply") from None
    return head_from_dict(data, source=path)


def head_from_dict(data: Mapping[str, Any], source: str | Path = "<head>") -> HeadSpec:
    """Validate a parsed head spec; ``source`` names the file in errors and anchors relative paths.

    The keys, types and defaults are those of :mod:`models.headschema`; here the values: non-empty names, finite
    and positive numbers, ranges, and references between tables (buses, actuators). Lengths and angles become SI.
    """
    src = Path(source)
    tables = check_head_file(data, str(source))  # unknown tables and keys, value types
    v = _Values(str(source))
    if tables.head is None:
        raise SpecError(v.source, "head", "missing required table")
    name = v.string(tables.head.name, "head.name")
    buses = _buses(v, tables.buses)
    actuators = _actuators(v, tables.actuators, data.get("actuators"), buses)
    groups = tuple(_group(v, gname, t, actuators) for gname, t in tables.groups.items())
    links = tuple(_link(v, lname, t, actuators) for lname, t in tables.links.items())
    paths = _paths(v, tables.paths, src)
    skin_material = None if tables.skin_material is None else dict(tables.skin_material)
    if skin_material is not None:
        check_material_table(skin_material, source)
    return HeadSpec(
        name=name,
        source=src,
        actuators=actuators,
        buses=buses,
        groups=groups,
        links=links,
        paths=paths,
        description=tables.head.description,
        sections=tables.sections,
        skin_material_table=skin_material,
        predictor_optional=tables.paths.predictor_optional,
    )


class _Values:
    """Value checks on typed tables that raise :class:`SpecError` naming the source, the key and the value."""

    def __init__(self, source: str) -> None:
        self.source = source

    def string(self, value: str, key: str) -> str:
        if not value:
            raise SpecError(self.source, key, "must be a non-empty string", value)
        return value

    def number(self, value: float | None, key: str, positive: bool = False) -> float:
        if value is None:
            raise SpecError(self.source, key, "missing required key")
        if not math.isfinite(value):
            raise SpecError(self.source, key, "must be a finite number", value)
        if positive and value <= 0:
            raise SpecError(self.source, key, "must be positive", value)
        return float(value)

    def at_least(self, value: int, key: str, minimum: int) -> int:
        if value < minimum:
            raise SpecError(self.source, key, f"must be at least {minimum}", value)
        return value

    def choice(self, value: str, key: str, options: tuple[str, ...]) -> Any:
        if value not in options:
            raise SpecError(self.source, key, f"must be one of {', '.join(options)}", value)
        return value

    def names(self, value: list[str], key: str, known: Mapping[str, ActuatorSpec], min_len: int) -> tuple[str, ...]:
        if len(value) < min_len:
            raise SpecError(self.source, key, f"needs at least {min_len} actuator(s)", value)
        if len(set(value)) != len(value):
            raise SpecError(self.source, key, "lists an actuator twice", value)
        for x in value:
            if x not in known:
                raise SpecError(self.source, key, "unknown actuator", x)
        return tuple(value)


def _buses(v: _Values, tables: Mapping[str, BusTable] | None) -> dict[str, BusSpec]:
    """The ``[buses.NAME]`` tables: at least one, each with a driver name."""
    if tables is None:
        raise SpecError(v.source, "buses", "missing required table")
    buses: dict[str, BusSpec] = {}
    for bus_name, t in tables.items():
        key = f"buses.{bus_name}"
        driver = v.string(t.driver, f"{key}.driver")
        heartbeat = None if t.heartbeat is None else _heartbeat(v, t.heartbeat, key, t.options)
        late, fault = _feedback_limits(v, t, key)
        buses[bus_name] = BusSpec(bus_name, driver, dict(t.options), t.simulated, heartbeat, late, fault)
    if not buses:
        raise SpecError(v.source, "buses", "a head needs at least one bus")
    return buses


def _feedback_limits(v: _Values, t: BusTable, key: str) -> tuple[float | None, float | None]:
    """``feedback_timeout_s`` and ``feedback_fault_s``: positive when given, the fault limit above the event's."""
    late = None if t.feedback_timeout_s is None else v.number(
        t.feedback_timeout_s, f"{key}.feedback_timeout_s", positive=True)
    fault = None if t.feedback_fault_s is None else v.number(
        t.feedback_fault_s, f"{key}.feedback_fault_s", positive=True)
    if late is not None and fault is not None and fault <= late:
        raise SpecError(v.source, f"{key}.feedback_fault_s", f"must be longer than feedback_timeout_s ({late:g} s)",
                        fault)
    return late, fault


def _heartbeat(v: _Values, t: HeartbeatTable, key: str, options: Mapping[str, Any]) -> HeartbeatSpec:
    """``[buses.NAME.heartbeat]``: a positive period, and a timeout above it (default two periods)."""
    for old in ("heartbeat_period_s", "heartbeat_timeout_s"):
        if old in options:
            raise SpecError(v.source, f"{key}.options.{old}", f"set the heartbeat in [{key}.heartbeat] only")
    period = v.number(t.period_s, f"{key}.heartbeat.period_s", positive=True)
    if not 0.001 <= period <= 65.535:
        raise SpecError(v.source, f"{key}.heartbeat.period_s", "must be 0.001..65.535 s", period)
    timeout = HEARTBEAT_TIMEOUT_PERIODS * period if t.timeout_s is None else v.number(
        t.timeout_s, f"{key}.heartbeat.timeout_s", positive=True)
    if timeout <= period:
        raise SpecError(v.source, f"{key}.heartbeat.timeout_s", f"must be longer than period_s ({period:g} s)",
                        timeout)
    return HeartbeatSpec(period, timeout)


def _actuators(v: _Values, tables: list[ActuatorTable] | None, raw: Any, buses: Mapping[str, BusSpec]
               ) -> tuple[ActuatorSpec, ...]:
    """The ``[[actuators]]`` array: at least one, names unique, device ids unique per bus."""
    if not tables:
        raise SpecError(v.source, "actuators", "must be a non-empty array of tables ([[actuators]])", raw)
    actuators: dict[str, ActuatorSpec] = {}
    seen_ids: dict[tuple[str, int], str] = {}
    for i, t in enumerate(tables):
        act = _actuator(v, t, i, buses)
        if act.name in actuators:
            raise SpecError(v.source, f"actuators[{i}] ({act.name}).name", "duplicate actuator name", act.name)
        other = seen_ids.get((act.bus, act.device_id))
        if other is not None:
            raise SpecError(
                v.source, f"actuators[{i}] ({act.name}).id", f"duplicate device id on bus {act.bus!r} (also {other!r})",
                act.device_id,
            )
        seen_ids[(act.bus, act.device_id)] = act.name
        actuators[act.name] = act
    return tuple(actuators.values())


def _actuator(v: _Values, t: ActuatorTable, i: int, buses: Mapping[str, BusSpec]) -> ActuatorSpec:
    """One actuator: its bus exists, min < neutral-range < max, positive rates and gear; values to SI."""
    name = v.string(t.name, f"actuators[{i}].name")
    key = f"actuators[{i}] ({name})"
    v.string(t.bus, f"{key}.bus")
    if t.bus not in buses:
        raise SpecError(v.source, f"{key}.bus", f"no such bus; defined: {', '.join(sorted(buses))}", t.bus)
    device_id = v.at_least(t.id, f"{key}.id", 0)
    unit = v.choice(t.unit, f"{key}.unit", tuple(UNITS))
    kind, scale, _ = UNITS[unit]
    lo = v.number(t.min, f"{key}.min")
    hi = v.number(t.max, f"{key}.max")
    if lo >= hi:
        raise SpecError(v.source, f"{key}.min", f"must be below max ({hi!r})", lo)
    neutral = min(max(0.0, lo), hi) if t.neutral is None else v.number(t.neutral, f"{key}.neutral")
    if not lo <= neutral <= hi:
        raise SpecError(v.source, f"{key}.neutral", f"must lie within [{lo}, {hi}]", neutral)
    vmax = v.number(t.max_velocity, f"{key}.max_velocity", positive=True)
    amax = v.number(t.max_acceleration, f"{key}.max_acceleration", positive=True)
    cpr = v.at_least(t.counts_per_rev, f"{key}.counts_per_rev", 1)
    gear = v.number(t.gear_ratio, f"{key}.gear_ratio", positive=True)
    if t.direction not in (1, -1):
        raise SpecError(v.source, f"{key}.direction", "must be 1 or -1", t.direction)
    max_fe = None if t.max_following_error is None else scale * v.number(
        t.max_following_error, f"{key}.max_following_error", positive=True)
    fe_time = None if t.following_error_time_s is None else v.number(
        t.following_error_time_s, f"{key}.following_error_time_s", positive=True)
    return ActuatorSpec(
        name=name, bus=t.bus, device_id=device_id, unit=unit, kind=kind,
        min=lo * scale, max=hi * scale, neutral=neutral * scale,
        max_velocity=vmax * scale, max_acceleration=amax * scale,
        counts_per_rev=cpr, gear_ratio=gear, direction=t.direction, zero_count=t.zero_count, options=dict(t.options),
        max_following_error=max_fe, following_error_time_s=fe_time,
    )


def _group(v: _Values, gname: str, t: GroupTable, actuators: tuple[ActuatorSpec, ...]) -> GroupSpec:
    """``[groups.NAME]``: a kind, two or more known actuators, a gain per actuator, a spread for ``coupled``."""
    key = f"groups.{gname}"
    by_name = {a.name: a for a in actuators}
    kind = v.choice(t.kind, f"{key}.kind", GROUP_KINDS)
    members = v.names(t.actuators, f"{key}.actuators", by_name, min_len=2)
    gains_raw = t.gains
    if gains_raw is None:
        gains_raw = [1.0] + [-1.0] * (len(members) - 1) if kind == "mirror" else [1.0] * len(members)
    if len(gains_raw) != len(members):
        raise SpecError(v.source, f"{key}.gains", f"must list {len(members)} numbers", gains_raw)
    gains = tuple(v.number(g, f"{key}.gains[{j}]") for j, g in enumerate(gains_raw))
    spread = None
    if kind == "coupled":
        units = {by_name[m].unit for m in members}
        if len(units) != 1:
            raise SpecError(v.source, f"{key}.actuators", "coupled actuators must share a unit", sorted(units))
        spread = v.number(t.max_spread, f"{key}.max_spread", positive=True) * by_name[members[0]].unit_scale
    return GroupSpec(gname, kind, members, gains, spread)


def _link(v: _Values, lname: str, t: LinkTable, actuators: tuple[ActuatorSpec, ...]) -> LinkSpec:
    """``[links.NAME]``: the actuators that move it (none for a rigid link) and its node set (default: its name)."""
    key = f"links.{lname}"
    if t.actuators is msgspec.UNSET and not t.rigid:
        raise SpecError(v.source, f"{key}.actuators", "missing required key")
    given = [] if t.actuators is msgspec.UNSET else t.actuators
    members = v.names(given, f"{key}.actuators", {a.name: a for a in actuators}, 0 if t.rigid else 1)
    if t.rigid and members:
        raise SpecError(v.source, f"{key}.actuators", "a rigid link has no actuators", list(members))
    return LinkSpec(lname, members, lname if t.node_set is None else t.node_set, t.rigid)


def _paths(v: _Values, t: PathsTable, src: Path) -> dict[str, Path]:
    """``[paths]``: the files given, resolved beside the head file."""
    paths: dict[str, Path] = {}
    for pkey in t.__struct_fields__:
        raw = getattr(t, pkey)
        if pkey == "predictor_optional" or raw is None:
            continue
        if not raw:
            raise SpecError(v.source, f"paths.{pkey}", "must be a non-empty path string", raw)
        p = Path(raw)
        paths[pkey] = p if p.is_absolute() else (src.parent / p).resolve()
    return paths
