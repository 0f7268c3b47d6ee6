"""The typed shape of a head spec TOML file: which tables and keys exist, the type of each value and its default.

This is the one declaration of a head file's keys. :func:`check_head_file` converts the file's tables (with msgspec)
into these types before :mod:`models.headspec` checks their values and builds the :class:`~models.headspec.HeadSpec`
from them, so a misspelled table (``[saftey]``) or key (``max_velocty``) is refused, naming the file, the table or key
and what is allowed, instead of being silently ignored. Value ranges and cross-references (a bus that exists, min
below max) are checked there. The keys of ``[runtime]``, ``[safety]`` and ``[api]`` belong to the daemon
(``runtime.config``) and are checked by it.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgspec

from models.errors import SpecError


class _Table(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A TOML table whose keys are all known."""


class HeadTable(_Table, kw_only=True):
    name: str
    description: str = ""


class HeartbeatTable(_Table, kw_only=True):
    """``[buses.NAME.heartbeat]``: how often each device sends its heartbeat (CANopen: the producer time 0x1017, which
    the driver writes) and how long the driver waits for one before it faults the bus (default two periods)."""

    period_s: float
    timeout_s: float | None = None


class BusTable(_Table, kw_only=True):
    """``[buses.NAME]``: the driver and its options; how old the devices' newest feedback may grow before the core
    says so (``feedback_timeout_s``, an event) and before it faults the head (``feedback_fault_s``)."""

    driver: str
    options: dict[str, Any] = {}
    simulated: bool = False
    heartbeat: HeartbeatTable | None = None
    feedback_timeout_s: float | None = None
    feedback_fault_s: float | None = None


class ActuatorTable(_Table, kw_only=True):
    name: str
    bus: str
    id: int
    unit: str
    min: float
    max: float
    neutral: float | None = None
    max_velocity: float
    max_acceleration: float
    counts_per_rev: int = 4096
    gear_ratio: float = 1.0
    direction: int = 1
    zero_count: int = 0
    max_following_error: float | None = None
    following_error_time_s: float | None = None
    options: dict[str, Any] = {}


class GroupTable(_Table, kw_only=True):
    kind: str
    actuators: list[str]
    gains: list[float] | None = None
    max_spread: float | None = None


class LinkTable(_Table, kw_only=True):
    actuators: list[str] | msgspec.UnsetType = msgspec.UNSET  # required unless the link is rigid
    node_set: str | None = None
    rigid: bool = False


class PathsTable(_Table, kw_only=True):
    """Files of learned models, relative to the head file. Without ``predictor_optional`` a missing predictor file
    stops the daemon at start-up; with it the daemon runs without the ``arkit.*`` target channels."""

    predictor: str | None = None
    linkmap: str | None = None
    skin_guard: str | None = None  # attachment footprint of the skin for the strain guard
    mechanism: str | None = None  # bodies, joints, couplers, motors (models/mechanism_file.py)
    predictor_optional: bool = False


class SkinTable(_Table, kw_only=True):
    """``[skin]``: tuning of the skin target solver (see ``runtime.skin``)."""

    strain_min: float | None = None
    strain_max: float | None = None
    smoothness_mm: float | None = None
    iterations_per_frame: int | None = None
    matrix_rank: int | None = None  # frame solve: rank per axis of the Gauss-Newton matrix (default: exact)
    radius_mm: float | None = None  # strain guard: smoothing neighbourhood (models.strain_guard)
    band_mm: float | None = None  # strain guard: band left out around attachment rims
    reference: str | None = None  # strain guard: "rest" or "neutral"


class OscTable(_Table, kw_only=True):
    """``[inputs.osc]``: an OSC server (``runtime.inputs.osc``); ``[inputs.osc.map]`` maps addresses to channels."""

    bind: str = "127.0.0.1:9000"  # UDP host:port
    tcp: str | None = None  # also serve OSC 1.1 over TCP (SLIP framing) on this host:port
    map: dict[str, str] = {}  # "/face/jaw" = "jaw"; "/face/arkit/*" = "arkit.*"
    control_prefix: str = "/likeness"  # control addresses: PREFIX/enable, /disable, /play, /stop, /estop
    control_allow: list[str] = []  # sender addresses allowed to use the control addresses (empty: none)
    allow_remote: bool = False  # binding beyond loopback needs this
    watchdog: bool = True  # the stream watchdog on loss (false: the values hold until another source takes over)


class SacnSlotTable(_Table, kw_only=True):
    """One ``[[inputs.sacn.slots]]`` entry: DMX slot(s) onto a channel's range."""

    channel: str
    slot: int | None = None  # 1-based, relative to the start address; default: right after the previous entry
    bits: int = 8  # 8 or 16 (coarse slot, then fine)
    range: list[float] | None = None  # channel value at DMX 0 and at full; default: the actuator's [min, max]


class SacnTable(_Table, kw_only=True):
    """``[inputs.sacn]``: an sACN (E1.31) receiver of one universe (``runtime.inputs.sacn``)."""

    bind: str = "127.0.0.1"  # the address to receive on (unicast), or the interface for multicast
    port: int = 5568
    universe: int = 1
    start: int = 1  # DMX start address of the head's first slot
    slots: list[dict[str, Any]] = []
    merge: str = "htp"  # between sources of the same (highest) priority: "htp" or "ltp"
    source_timeout_s: float = 2.5  # a source silent this long is dropped from the merge (E1.31 data loss)
    multicast: bool = False  # join the universe's multicast group on the bind interface
    allow_remote: bool = False


class TimecodeTable(_Table, kw_only=True):
    """``[inputs.timecode]``: MIDI timecode chase (``runtime.inputs.mtc``)."""

    bind: str | None = "127.0.0.1:5004"  # a TCP MIDI port (mido.sockets) to listen on
    midi_port: str | None = None  # or a MIDI input port by name (needs a mido backend, e.g. python-rtmidi)
    rate: str = "25"  # the frame rate offsets are written in: "24", "25", "29.97" (drop frame), "30"
    clips: dict[str, Any] = {}  # clip name = chase offset ("01:00:10:00", or seconds)
    freewheel_s: float = 2.0
    dropout_s: float = 0.15
    jump_s: float = 0.25
    lock_samples: int = 3
    allow_remote: bool = False


class InputsTable(_Table, kw_only=True):
    """``[inputs]``: show-control inputs beside the ZeroMQ protocol (``docs/show_control.md``)."""

    osc: dict[str, Any] | None = None
    sacn: dict[str, Any] | None = None
    timecode: dict[str, Any] | None = None


class HeadFile(_Table, kw_only=True):
    """The top level. Required tables are optional here so that :mod:`models.headspec` names them when missing."""

    head: dict[str, Any] | None = None
    buses: dict[str, Any] | None = None
    actuators: Any = None
    groups: dict[str, Any] = {}
    links: dict[str, Any] = {}
    paths: dict[str, Any] = {}
    skin_material: dict[str, Any] | None = None
    skin: dict[str, Any] | None = None
    runtime: dict[str, Any] = {}
    safety: dict[str, Any] = {}
    api: dict[str, Any] = {}
    inputs: dict[str, Any] = {}


def table_names() -> tuple[str, ...]:
    """Every top-level table a head file may hold."""
    return HeadFile.__struct_fields__


_UNKNOWN = re.compile(r"Object contains unknown field `(?P<field>[^`]*)`")
_MISSING = re.compile(r"Object missing required field `(?P<field>[^`]*)`")
_AT = re.compile(r" - at `\$(?P<path>[^`]*)`$")


def _spec_error(exc: msgspec.ValidationError, source: str, key: str, cls: type) -> SpecError:
    text = str(exc)
    at = _AT.search(text)
    sub = at.group("path") if at else ""
    text = text[: at.start()] if at else text
    where = f"{key}{sub}" if key else sub.lstrip(".")
    if m := _UNKNOWN.match(text):
        name = m.group("field")
        if not where:
            return SpecError(source, name, f"unknown table or top-level key; known tables: {', '.join(table_names())}")
        allowed = cls.__struct_fields__ if not sub else ()
        hint = f"; allowed: {', '.join(sorted(allowed))}" if allowed else ""
        return SpecError(source, f"{where}.{name}", f"unknown key{hint}")
    if m := _MISSING.match(text):
        return SpecError(source, f"{where}.{m.group('field')}" if where else m.group("field"), "missing required key")
    expected = text.replace("`", "").replace("Expected", "expected").replace("object", "table")
    return SpecError(source, where or "(file)", expected)


def _convert(raw: Any, cls: type, source: str, key: str) -> Any:
    try:
        return msgspec.convert(raw, cls, strict=True)
    except msgspec.ValidationError as exc:
        raise _spec_error(exc, source, key, cls) from None


#: The tables :class:`~models.headspec.HeadSpec` is built from; every other table belongs to another layer.
SPEC_TABLES = frozenset({"head", "buses", "actuators", "groups", "links", "paths", "skin_material"})


@dataclass(frozen=True)
class HeadTables:
    """A head file's tables converted to their types (file units, defaults filled in).

    ``head`` and ``buses`` are None when missing and ``actuators`` when not an array: :mod:`models.headspec` names
    them. ``sections`` holds the tables other layers own (``runtime``, ``safety``, ``api``, ``inputs``, ``skin``), as
    parsed.
    """

    head: HeadTable | None
    buses: dict[str, BusTable] | None
    actuators: list[ActuatorTable] | None
    groups: dict[str, GroupTable]
    links: dict[str, LinkTable]
    paths: PathsTable
    skin_material: dict[str, Any] | None
    sections: dict[str, dict[str, Any]]


def check_head_file(data: Mapping[str, Any], source: str) -> HeadTables:
    """Check the tables, keys and value types of a parsed head file and convert them; SpecError naming the file
    and key."""
    if not isinstance(data, Mapping):
        raise SpecError(source, "(file)", "a head spec must be a TOML table")
    top = _convert(dict(data), HeadFile, source, "")
    head = _convert(top.head, HeadTable, source, "head") if top.head is not None else None
    buses = None if top.buses is None else {
        name: _convert(raw, BusTable, source, f"buses.{name}") for name, raw in top.buses.items()}
    actuators = None
    if isinstance(top.actuators, list):
        actuators = []
        for i, raw in enumerate(top.actuators):
            label = f"actuators[{i}]"
            if isinstance(raw, Mapping) and isinstance(raw.get("name"), str):
                label += f" ({raw['name']})"
            actuators.append(_convert(raw, ActuatorTable, source, label))
    groups = {name: _convert(raw, GroupTable, source, f"groups.{name}") for name, raw in top.groups.items()}
    links = {name: _convert(raw, LinkTable, source, f"links.{name}") for name, raw in top.links.items()}
    paths = _convert(top.paths, PathsTable, source, "paths")
    if top.skin is not None:
        _convert(top.skin, SkinTable, source, "skin")
    _check_inputs(top.inputs, source)
    return HeadTables(head, buses, actuators, groups, links, paths, top.skin_material,
                      {key: value for key, value in data.items() if key not in SPEC_TABLES})


def _check_inputs(raw: dict[str, Any], source: str) -> None:
    """The ``[inputs]`` tables' keys and types (their values are checked by ``runtime.inputs.config``)."""
    inputs = _convert(raw, InputsTable, source, "inputs")
    for key, cls in (("osc", OscTable), ("sacn", SacnTable), ("timecode", TimecodeTable)):
        sub = getattr(inputs, key)
        if sub is not None:
            table = _convert(sub, cls, source, f"inputs.{key}")
            if key == "sacn":
                for i, slot in enumerate(table.slots):
                    _convert(slot, SacnSlotTable, source, f"inputs.sacn.slots[{i}]")
