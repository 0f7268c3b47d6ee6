"""Object dictionary of the emulated CiA 402 drive, built in code and exportable as an EDS.

The dictionary mirrors what a small servo drive publishes: the CiA 301 communication objects a
master needs (identity, heartbeat, four RPDO and four TPDO communication and mapping records, since
masters such as canopen's ``BaseNode402`` read all of them) and the CiA 402 objects for the state
machine, cyclic synchronous position (mode 8) and profile position (mode 1). Positions are encoder
counts, velocities counts/s, accelerations counts/s², currents and torques per mille of rated.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from canopen import ObjectDictionary, export_od
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.objectdictionary.datatypes import (
    INTEGER8,
    INTEGER16,
    INTEGER32,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    VISIBLE_STRING,
)

DEVICE_TYPE = 0x00020192  # CiA 402 servo drive
VENDOR_ID = 0x4C4B4E53  # "LKNS", not a registered vendor id: emulated hardware only
PRODUCT_CODE = 0x00000402
REVISION = 0x00010000
DEVICE_NAME = "Likeness emulated CiA 402 drive"

MODE_PROFILE_POSITION = 1
MODE_CSP = 8
SUPPORTED_MODES = 0x0001 | 0x0080  # profile position + cyclic synchronous position

PDO_DISABLED = 0x80000000

#: Default PDO layout (node-id relative COB-IDs as in the CiA 301 pre-defined connection set):
#: (COB-ID base, transmission type, enabled, [(index, subindex, bits), ...]).
DEFAULT_RPDOS: tuple[tuple[int, int, bool, tuple[tuple[int, int, int], ...]], ...] = (
    (0x200, 255, True, ((0x6040, 0, 16),)),
    (0x300, 255, True, ((0x6040, 0, 16), (0x6060, 0, 8))),
    (0x400, 1, True, ((0x6040, 0, 16), (0x607A, 0, 32))),
    (0x500, 1, False, ((0x607A, 0, 32),)),
)
DEFAULT_TPDOS: tuple[tuple[int, int, bool, tuple[tuple[int, int, int], ...]], ...] = (
    (0x180, 255, True, ((0x6041, 0, 16),)),
    (0x280, 255, True, ((0x6041, 0, 16), (0x6061, 0, 8))),
    (0x380, 1, True, ((0x6041, 0, 16), (0x6064, 0, 32))),
    (0x480, 1, False, ((0x6064, 0, 32), (0x606C, 0, 32))),
)


def _var(
    name: str,
    index: int,
    subindex: int,
    data_type: int,
    access: str,
    default: int | str | None,
    *,
    pdo: bool = False,
    unit: str = "",
) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    if isinstance(default, int) and default < 0:
        # canopen's EDS writer formats negative integers as "0x-…", which no reader parses.
        var.default_raw = str(default)
    var.pdo_mappable = pdo
    var.unit = unit
    return var


def _add(od: ObjectDictionary, var: ODVariable) -> None:
    od.add_object(var)


def _record(od: ObjectDictionary, name: str, index: int, subs: list[ODVariable], *, array: bool = False) -> None:
    rec = ODArray(name, index) if array else ODRecord(name, index)
    for sub in subs:
        rec.add_member(sub)
    od.add_object(rec)


def build_od(
    node_id: int,
    *,
    heartbeat_ms: int = 0,
    following_error_window: int = 5000,
    max_velocity: int = 400_000,
) -> ObjectDictionary:
    """Object dictionary of one emulated drive with node id ``node_id`` (COB-IDs resolved)."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"node id must be 1..127, got {node_id}")
    od = ObjectDictionary()
    od.node_id = node_id
    od.bitrate = 1_000_000

    # ---- CiA 301 communication area
    _add(od, _var("Device type", 0x1000, 0, UNSIGNED32, "ro", DEVICE_TYPE))
    _add(od, _var("Error register", 0x1001, 0, UNSIGNED8, "ro", 0, pdo=True))
    _add(od, _var("Manufacturer device name", 0x1008, 0, VISIBLE_STRING, "const", DEVICE_NAME))
    _add(od, _var("Producer heartbeat time", 0x1017, 0, UNSIGNED16, "rw", heartbeat_ms, unit="ms"))
    _record(od, "Identity object", 0x1018, [
        _var("Highest sub-index supported", 0x1018, 0, UNSIGNED8, "const", 4),
        _var("Vendor-ID", 0x1018, 1, UNSIGNED32, "ro", VENDOR_ID),
        _var("Product code", 0x1018, 2, UNSIGNED32, "ro", PRODUCT_CODE),
        _var("Revision number", 0x1018, 3, UNSIGNED32, "ro", REVISION),
        _var("Serial number", 0x1018, 4, UNSIGNED32, "ro", 0x10000 + node_id),
    ])
    for n, (base, trans, enabled, entries) in enumerate(DEFAULT_RPDOS):
        cob = base + node_id | (0 if enabled else PDO_DISABLED)
        _record(od, f"RPDO{n + 1} communication parameter", 0x1400 + n, [
            _var("Highest sub-index supported", 0x1400 + n, 0, UNSIGNED8, "const", 2),
            _var("COB-ID used by RPDO", 0x1400 + n, 1, UNSIGNED32, "rw", cob),
            _var("Transmission type", 0x1400 + n, 2, UNSIGNED8, "rw", trans),
        ])
        _mapping(od, f"RPDO{n + 1} mapping parameter", 0x1600 + n, entries)
    for n, (base, trans, enabled, entries) in enumerate(DEFAULT_TPDOS):
        cob = base + node_id | (0 if enabled else PDO_DISABLED)
        _record(od, f"TPDO{n + 1} communication parameter", 0x1800 + n, [
            _var("Highest sub-index supported", 0x1800 + n, 0, UNSIGNED8, "const", 5),
            _var("COB-ID used by TPDO", 0x1800 + n, 1, UNSIGNED32, "rw", cob),
            _var("Transmission type", 0x1800 + n, 2, UNSIGNED8, "rw", trans),
            _var("Inhibit time", 0x1800 + n, 3, UNSIGNED16, "rw", 0, unit="100 us"),
            _var("Event timer", 0x1800 + n, 5, UNSIGNED16, "rw", 50 if trans >= 254 else 0, unit="ms"),
        ])
        _mapping(od, f"TPDO{n + 1} mapping parameter", 0x1A00 + n, entries)

    # ---- CiA 402 device profile
    p = {"pdo": True}
    _add(od, _var("Error code", 0x603F, 0, UNSIGNED16, "ro", 0, **p))
    _add(od, _var("Controlword", 0x6040, 0, UNSIGNED16, "rw", 0, **p))
    _add(od, _var("Statusword", 0x6041, 0, UNSIGNED16, "ro", 0, **p))
    _add(od, _var("Quick stop option code", 0x605A, 0, INTEGER16, "rw", 2))
    _add(od, _var("Fault reaction option code", 0x605E, 0, INTEGER16, "rw", 2))
    _add(od, _var("Modes of operation", 0x6060, 0, INTEGER8, "rw", 0, **p))
    _add(od, _var("Modes of operation display", 0x6061, 0, INTEGER8, "ro", 0, **p))
    _add(od, _var("Position demand value", 0x6062, 0, INTEGER32, "ro", 0, unit="counts", **p))
    _add(od, _var("Position actual value", 0x6064, 0, INTEGER32, "ro", 0, unit="counts", **p))
    _add(od, _var("Following error window", 0x6065, 0, UNSIGNED32, "rw", following_error_window, unit="counts"))
    _add(od, _var("Following error time out", 0x6066, 0, UNSIGNED16, "rw", 10, unit="ms"))
    _add(od, _var("Position window", 0x6067, 0, UNSIGNED32, "rw", 20, unit="counts"))
    _add(od, _var("Position window time", 0x6068, 0, UNSIGNED16, "rw", 0, unit="ms"))
    _add(od, _var("Velocity actual value", 0x606C, 0, INTEGER32, "ro", 0, unit="counts/s", **p))
    _add(od, _var("Max current", 0x6073, 0, UNSIGNED16, "rw", 2000, unit="per mille"))
    _add(od, _var("Motor rated current", 0x6075, 0, UNSIGNED32, "rw", 2000, unit="mA"))
    _add(od, _var("Motor rated torque", 0x6076, 0, UNSIGNED32, "rw", 200, unit="mNm"))
    _add(od, _var("Torque actual value", 0x6077, 0, INTEGER16, "ro", 0, unit="per mille", **p))
    _add(od, _var("Current actual value", 0x6078, 0, INTEGER16, "ro", 0, unit="per mille", **p))
    _add(od, _var("Target position", 0x607A, 0, INTEGER32, "rw", 0, unit="counts", **p))
    _record(od, "Software position limit", 0x607D, [
        _var("Highest sub-index supported", 0x607D, 0, UNSIGNED8, "const", 2),
        _var("Min position limit", 0x607D, 1, INTEGER32, "rw", -(2**31)),
        _var("Max position limit", 0x607D, 2, INTEGER32, "rw", 2**31 - 1),
    ], array=True)
    _add(od, _var("Max profile velocity", 0x607F, 0, UNSIGNED32, "rw", max_velocity, unit="counts/s"))
    _add(od, _var("Profile velocity", 0x6081, 0, UNSIGNED32, "rw", 20_000, unit="counts/s", **p))
    _add(od, _var("Profile acceleration", 0x6083, 0, UNSIGNED32, "rw", 200_000, unit="counts/s2"))
    _add(od, _var("Profile deceleration", 0x6084, 0, UNSIGNED32, "rw", 200_000, unit="counts/s2"))
    _add(od, _var("Quick stop deceleration", 0x6085, 0, UNSIGNED32, "rw", 1_000_000, unit="counts/s2"))
    _record(od, "Interpolation time period", 0x60C2, [
        _var("Highest sub-index supported", 0x60C2, 0, UNSIGNED8, "const", 2),
        _var("Interpolation time period value", 0x60C2, 1, UNSIGNED8, "rw", 10),
        _var("Interpolation time index", 0x60C2, 2, INTEGER8, "rw", -3),
    ])
    _add(od, _var("Following error actual value", 0x60F4, 0, INTEGER32, "ro", 0, unit="counts", **p))
    _add(od, _var("Supported drive modes", 0x6502, 0, UNSIGNED32, "ro", SUPPORTED_MODES))
    return od


def _mapping(od: ObjectDictionary, name: str, index: int, entries: tuple[tuple[int, int, int], ...]) -> None:
    subs = [_var("Number of mapped objects", index, 0, UNSIGNED8, "rw", len(entries))]
    for sub in range(1, 9):
        value = 0
        if sub <= len(entries):
            obj, obj_sub, bits = entries[sub - 1]
            value = obj << 16 | obj_sub << 8 | bits
        subs.append(_var(f"Mapped object {sub}", index, sub, UNSIGNED32, "rw", value))
    _record(od, name, index, subs)


def write_eds(path: str | os.PathLike[str], node_id: int = 1, **od_options: int) -> Path:
    """Write the drive's object dictionary as an EDS file (atomically) and return its path."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        export_od(build_od(node_id, **od_options), tmp, doc_type="eds")
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target
