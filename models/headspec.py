"""Head specification (TOML): actuators, buses, groups, links and the paths of learned models.

Configs use operator units (degrees for rotary actuators, millimetres for linear ones); the loaded
:class:`HeadSpec` is in SI (radians, metres, seconds). Every validation error names the file, the
key and the bad value.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from models.errors import SpecError
from models.headschema import check_head_file
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
    """One actuator, in SI. ``unit`` is the config unit the operator sees (deg or mm)."""

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
    counts_per_rev: int = 4096
    gear_ratio: float = 1.0
    direction: int = 1
    zero_count: int = 0
    options: Mapping[str, Any] = field(default_factory=dict)

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
    simulated: bool = False
    heartbeat: HeartbeatSpec | None = None

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
    max_spread: float | None = None  # SI; only for "coupled"


@dataclass(frozen=True)
class LinkSpec:
    """An attachment link of the skin, moved by ``actuators`` (none for rigid skull links)."""

    name: str
    actuators: tuple[str, ...]
    node_set: str
    rigid: bool = False


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
    description: str = ""
    #: Raw tables owned by other layers (e.g. ``runtime``, ``safety``, ``calibration``), validated there.
    sections: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    #: The ``[skin_material]`` table (checked; a fit file it names is read by :meth:`skin_material`).
    skin_material_table: Mapping[str, Any] | None = None
    #: ``[paths] predictor_optional``: run without the predictor's target channels when its file is missing.
    predictor_optional: bool = False

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
    """Validate a parsed head spec; ``source`` names the file in errors and anchors relative paths."""
    src = Path(source)
    check_head_file(data, str(source))  # unknown tables and keys, value types
    v = _Validator(str(source))
    head = v.table(data, "head")
    name = v.string(head, "head.name")
    description = v.string(head, "head.description", default="")

    buses: dict[str, BusSpec] = {}
    for bus_name, raw in v.table(data, "buses").items():
        key = f"buses.{bus_name}"
        raw = v.as_table(raw, key)
        driver = v.string(raw, f"{key}.driver")
        options = v.as_table(raw.get("options", {}), f"{key}.options")
        simulated = v.boolean(raw, f"{key}.simulated", default=False)
        v.no_extra(raw, key, {"driver", "options", "simulated", "heartbeat"})
        heartbeat = _heartbeat(v, raw, key, options)
        buses[bus_name] = BusSpec(bus_name, driver, dict(options), simulated, heartbeat)
    if not buses:
        raise SpecError(v.source, "buses", "a head needs at least one bus")

    actuators: list[ActuatorSpec] = []
    seen_ids: dict[tuple[str, int], str] = {}
    raw_acts = data.get("actuators")
    if not isinstance(raw_acts, list) or not raw_acts:
        raise SpecError(v.source, "actuators", "must be a non-empty array of tables ([[actuators]])", raw_acts)
    for i, raw in enumerate(raw_acts):
        act = _actuator(v, v.as_table(raw, f"actuators[{i}]"), i, buses)
        if any(a.name == act.name for a in actuators):
            raise SpecError(v.source, f"actuators[{i}] ({act.name}).name", "duplicate actuator name", act.name)
        other = seen_ids.get((act.bus, act.device_id))
        if other is not None:
            raise SpecError(
                v.source, f"actuators[{i}] ({act.name}).id", f"duplicate device id on bus {act.bus!r} (also {other!r})",
                act.device_id,
            )
        seen_ids[(act.bus, act.device_id)] = act.name
        actuators.append(act)
    names = {a.name for a in actuators}
    by_name = {a.name: a for a in actuators}

    groups: list[GroupSpec] = []
    for gname, raw in v.table(data, "groups", required=False).items():
        key = f"groups.{gname}"
        raw = v.as_table(raw, key)
        kind = v.choice(raw, f"{key}.kind", GROUP_KINDS)
        members = v.names(raw, f"{key}.actuators", names, min_len=2)
        default_gains = [1.0] * len(members)
        if kind == "mirror":
            default_gains = [1.0] + [-1.0] * (len(members) - 1)
        gains_raw = raw.get("gains", default_gains)
        if not isinstance(gains_raw, list) or len(gains_raw) != len(members):
            raise SpecError(v.source, f"{key}.gains", f"must list {len(members)} numbers", gains_raw)
        gains = tuple(v.number_value(g, f"{key}.gains[{j}]") for j, g in enumerate(gains_raw))
        spread = None
        if kind == "coupled":
            units = {by_name[m].unit for m in members}
            if len(units) != 1:
                raise SpecError(v.source, f"{key}.actuators", "coupled actuators must share a unit", sorted(units))
            spread = v.number(raw, f"{key}.max_spread", positive=True) * by_name[members[0]].unit_scale
        v.no_extra(raw, key, {"kind", "actuators", "gains", "max_spread"})
        groups.append(GroupSpec(gname, kind, tuple(members), gains, spread))

    links: list[LinkSpec] = []
    for lname, raw in v.table(data, "links", required=False).items():
        key = f"links.{lname}"
        raw = v.as_table(raw, key)
        rigid = v.boolean(raw, f"{key}.rigid", default=False)
        members = v.names(raw, f"{key}.actuators", names, min_len=0 if rigid else 1)
        if rigid and members:
            raise SpecError(v.source, f"{key}.actuators", "a rigid link has no actuators", members)
        node_set = v.string(raw, f"{key}.node_set", default=lname)
        v.no_extra(raw, key, {"actuators", "node_set", "rigid"})
        links.append(LinkSpec(lname, tuple(members), node_set, rigid))

    paths: dict[str, Path] = {}
    raw_paths = dict(v.table(data, "paths", required=False))
    predictor_optional = v.boolean(raw_paths, "paths.predictor_optional", default=False)
    raw_paths.pop("predictor_optional", None)
    for pkey, raw in raw_paths.items():
        if not isinstance(raw, str) or not raw:
            raise SpecError(v.source, f"paths.{pkey}", "must be a non-empty path string", raw)
        p = Path(raw)
        paths[pkey] = p if p.is_absolute() else (src.parent / p).resolve()

    skin_material = None
    if "skin_material" in data:
        skin_material = dict(v.as_table(data["skin_material"], "skin_material"))
        check_material_table(skin_material, source)

    known = {"head", "buses", "actuators", "groups", "links", "paths", "skin_material"}
    sections = {}
    for key, value in data.items():
        if key in known:
            continue
        if not isinstance(value, dict):
            raise SpecError(v.source, key, "unknown top-level key", value)
        sections[key] = value
    return HeadSpec(
        name=name,
        source=src,
        actuators=tuple(actuators),
        buses=buses,
        groups=tuple(groups),
        links=tuple(links),
        paths=paths,
        description=description,
        sections=sections,
        skin_material_table=skin_material,
        predictor_optional=predictor_optional,
    )


_ACTUATOR_KEYS = {
    "name", "bus", "id", "unit", "min", "max", "neutral", "max_velocity", "max_acceleration",
    "counts_per_rev", "gear_ratio", "direction", "zero_count", "options",
}


def _actuator(v: _Validator, raw: Mapping[str, Any], i: int, buses: Mapping[str, BusSpec]) -> ActuatorSpec:
    key = f"actuators[{i}]"
    name = v.string(raw, f"{key}.name")
    key = f"actuators[{i}] ({name})"
    bus = v.string(raw, f"{key}.bus", field="bus")
    if bus not in buses:
        raise SpecError(v.source, f"{key}.bus", f"no such bus; defined: {', '.join(sorted(buses))}", bus)
    device_id = v.integer(raw, f"{key}.id", field="id", minimum=0)
    unit = v.choice(raw, f"{key}.unit", tuple(UNITS), field="unit")
    kind, scale, _ = UNITS[unit]
    lo = v.number(raw, f"{key}.min", field="min")
    hi = v.number(raw, f"{key}.max", field="max")
    if lo >= hi:
        raise SpecError(v.source, f"{key}.min", f"must be below max ({hi!r})", lo)
    neutral = v.number(raw, f"{key}.neutral", field="neutral", default=min(max(0.0, lo), hi))
    if not lo <= neutral <= hi:
        raise SpecError(v.source, f"{key}.neutral", f"must lie within [{lo}, {hi}]", neutral)
    vmax = v.number(raw, f"{key}.max_velocity", field="max_velocity", positive=True)
    amax = v.number(raw, f"{key}.max_acceleration", field="max_acceleration", positive=True)
    cpr = v.integer(raw, f"{key}.counts_per_rev", field="counts_per_rev", minimum=1, default=4096)
    gear = v.number(raw, f"{key}.gear_ratio", field="gear_ratio", positive=True, default=1.0)
    direction = v.integer(raw, f"{key}.direction", field="direction", default=1)
    if direction not in (1, -1):
        raise SpecError(v.source, f"{key}.direction", "must be 1 or -1", direction)
    zero = v.integer(raw, f"{key}.zero_count", field="zero_count", default=0)
    options = v.as_table(raw.get("options", {}), f"{key}.options")
    v.no_extra(raw, key, _ACTUATOR_KEYS)
    return ActuatorSpec(
        name=name, bus=bus, device_id=device_id, unit=unit, kind=kind,
        min=lo * scale, max=hi * scale, neutral=neutral * scale,
        max_velocity=vmax * scale, max_acceleration=amax * scale,
        counts_per_rev=cpr, gear_ratio=gear, direction=direction, zero_count=zero, options=dict(options),
    )


class _Validator:
    """Small typed getters that raise :class:`SpecError` naming the source and key."""

    def __init__(self, source: str) -> None:
        self.source = source

    def _get(self, raw: Mapping[str, Any], key: str, field: str | None, default: Any) -> Any:
        leaf = field or key.rsplit(".", 1)[-1]
        if leaf in raw:
            return raw[leaf]
        if default is not _REQUIRED:
            return default
        raise SpecError(self.source, key, "missing required key")

    def table(self, raw: Mapping[str, Any], key: str, required: bool = True) -> Mapping[str, Any]:
        if key not in raw:
            if required:
                raise SpecError(self.source, key, "missing required table")
            return {}
        return self.as_table(raw[key], key)

    def as_table(self, value: Any, key: str) -> Mapping[str, Any]:
        if not isinstance(value, dict):
            raise SpecError(self.source, key, "must be a table", value)
        return value

    def string(self, raw, key, field=None, default: Any = None) -> str:
        value = self._get(raw, key, field, _REQUIRED if default is None else default)
        if not isinstance(value, str) or (default is None and not value):
            raise SpecError(self.source, key, "must be a non-empty string", value)
        return value

    def boolean(self, raw, key, field=None, default: Any = None) -> bool:
        value = self._get(raw, key, field, _REQUIRED if default is None else default)
        if not isinstance(value, bool):
            raise SpecError(self.source, key, "must be true or false", value)
        return value

    def number_value(self, value: Any, key: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SpecError(self.source, key, "must be a finite number", value)
        if positive and value <= 0:
            raise SpecError(self.source, key, "must be positive", value)
        return float(value)

    def number(self, raw, key, field=None, positive: bool = False, default: Any = None) -> float:
        value = self._get(raw, key, field, _REQUIRED if default is None else default)
        return self.number_value(value, key, positive)

    def integer(self, raw, key, field=None, minimum: int | None = None, default: Any = None) -> int:
        value = self._get(raw, key, field, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise SpecError(self.source, key, "must be an integer", value)
        if minimum is not None and value < minimum:
            raise SpecError(self.source, key, f"must be at least {minimum}", value)
        return value

    def choice(self, raw, key, options: tuple[str, ...], field=None) -> Any:
        value = self._get(raw, key, field, _REQUIRED)
        if value not in options:
            raise SpecError(self.source, key, f"must be one of {', '.join(options)}", value)
        return value

    def names(self, raw, key, known: set[str], min_len: int) -> list[str]:
        value = self._get(raw, key, None, [] if min_len == 0 else _REQUIRED)
        if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
            raise SpecError(self.source, key, "must be a list of actuator names", value)
        if len(value) < min_len:
            raise SpecError(self.source, key, f"needs at least {min_len} actuator(s)", value)
        if len(set(value)) != len(value):
            raise SpecError(self.source, key, "lists an actuator twice", value)
        for x in value:
            if x not in known:
                raise SpecError(self.source, key, "unknown actuator", x)
        return list(value)

    def no_extra(self, raw: Mapping[str, Any], key: str, allowed: set[str]) -> None:
        for k in raw:
            if k not in allowed:
                raise SpecError(self.source, f"{key}.{k}", f"unknown key; allowed: {', '.join(sorted(allowed))}")


_REQUIRED = object()


def _heartbeat(v: _Validator, raw: Mapping[str, Any], key: str, options: Mapping[str, Any]) -> HeartbeatSpec | None:
    """``[buses.NAME.heartbeat]``: a positive period, and a timeout above it (default two periods)."""
    if "heartbeat" not in raw:
        return None
    table = v.as_table(raw["heartbeat"], f"{key}.heartbeat")
    for old in ("heartbeat_period_s", "heartbeat_timeout_s"):
        if old in options:
            raise SpecError(v.source, f"{key}.options.{old}", f"set the heartbeat in [{key}.heartbeat] only")
    period = v.number(table, f"{key}.heartbeat.period_s", "period_s", positive=True)
    if not 0.001 <= period <= 65.535:
        raise SpecError(v.source, f"{key}.heartbeat.period_s", "must be 0.001..65.535 s", period)
    timeout = v.number(table, f"{key}.heartbeat.timeout_s", "timeout_s", positive=True,
                       default=HEARTBEAT_TIMEOUT_PERIODS * period)
    if timeout <= period:
        raise SpecError(v.source, f"{key}.heartbeat.timeout_s", f"must be longer than period_s ({period:g} s)",
                        timeout)
    return HeartbeatSpec(period, timeout)
