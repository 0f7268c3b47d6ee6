"""A redesigned head as a complete head folder: the config, the new mechanism file, its runtime link map, the skin
and the other assets, so ``likeness daemon --config DIR/head/head.toml`` runs it as it runs the original.

The mechanism file is written at the design's own neutral configuration (every motor at zero, the linkages
re-assembled with the new parameters): each body's points and axes are moved by its transform T(0, θ) there, so the
file's rods close at neutral; the attachment links keep their frames (the skin is mounted at neutral, see
:mod:`offline.design.mechanism_design_kin`). The written file is read back and checked: its link motion against the
design's at random poses (``file_vs_design_max_mm``), and the cubic link map against the mechanism
(``map_vs_mechanism_max_mm``; a quartic map where the cubic one is further than 0.05 mm from it).
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path
from models.mechanism_file import MechanismSpec
from models.rigid import matrix_to_rotvec

from .mechanism_design_kin import DesignedMechanism

#: How closely the runtime's link map must follow the mechanism (mm, over the whole range).
MAP_TOLERANCE_MM = 0.05
#: The head folder's link map: (degree, tabulated poses as a multiple of ``map_samples``), tried in turn until the
#: map is within MAP_TOLERANCE_MM of the mechanism. On the sample head's ring design the quintic map needed twice the
#: poses (0.051 mm from 300, 0.027 mm from 600; the quartic 0.063 mm).
MAP_TRIES = ((3, 1), (4, 1), (5, 2))

#: The head folder's entries copied as they are (when present), besides the ``[paths]`` files.
COPIED = ("skin", "performances", "material_fit.json", "predictor_report.json", "skin_guard_report.json")


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    return "[" + ", ".join(f"{float(x):.12g}" for x in v) + "]"


def _at(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return T[:3, :3] @ p + T[:3, 3]


def neutral_tables(dm: DesignedMechanism) -> dict[str, dict[str, dict[str, Any]]]:
    """The design's mechanism as file tables at its own neutral configuration (SI lengths, degrees)."""
    spec: MechanismSpec = dm.spec
    T0 = dm.T0
    bodies: dict[str, dict[str, Any]] = {}
    points: dict[str, list[np.ndarray]] = {n: [] for n in spec.bodies}
    for j in spec.joints.values():
        points[j.parent].append(_at(T0[j.child], j.anchor))
        points[j.child].append(_at(T0[j.child], j.anchor))
    for c in spec.couplers.values():
        if c.kind == "rod":
            points[c.a].append(_at(T0[c.a], c.a_point))
            points[c.b].append(_at(T0[c.b], c.b_point))
    for name, b in spec.bodies.items():
        rest = b.rest if b.node_set is not None else T0[name] @ b.rest
        o = rest[:3, 3]
        extent = max([b.extent] + [float(np.linalg.norm(p - o)) + 1e-3 for p in points[name]])
        row: dict[str, Any] = {"origin": o, "rotvec_deg": np.degrees(matrix_to_rotvec(rest[:3, :3])),
                               "extent": extent}
        if b.node_set is not None:
            row["node_set"] = b.node_set
        bodies[name] = row
    joints: dict[str, dict[str, Any]] = {}
    for name, j in spec.joints.items():
        row = {"kind": j.kind, "parent": j.parent, "child": j.child, "anchor": _at(T0[j.child], j.anchor)}
        if j.axis is not None:
            row["axis"] = T0[j.parent][:3, :3] @ j.axis
        row["actuated"] = j.actuated
        if j.tilt_axis is not None and j.tilt_rate:
            row["tilt_axis"] = T0[j.parent][:3, :3] @ j.tilt_axis
            row["tilt_deg_per_m"] = math.degrees(j.tilt_rate)
        joints[name] = row
    couplers: dict[str, dict[str, Any]] = {}
    for name, c in spec.couplers.items():
        if c.kind == "rod":
            couplers[name] = {"kind": "rod", "a": c.a, "a_point": _at(T0[c.a], c.a_point), "b": c.b,
                              "b_point": _at(T0[c.b], c.b_point), "length": c.length}
        else:
            couplers[name] = {"kind": "gear", "a": c.a, "b": c.b, "axis": c.axis, "ratio": c.ratio}
    motors = {name: {"joint": m.joint, "ratio": m.ratio} for name, m in spec.motors.items()}
    return {"mechanism": {"name": spec.name, "ground": spec.ground, "closure_tolerance_m": spec.tolerance},
            "bodies": bodies, "joints": joints, "couplers": couplers, "motors": motors}


def mechanism_text(tables: Mapping[str, Mapping[str, Any]], header: str = "") -> str:
    """The tables as a mechanism TOML file."""
    lines = [f"# {line}" for line in header.splitlines()]
    lines += ["", "[mechanism]"] + [f"{k} = {_fmt(v)}" for k, v in tables["mechanism"].items()]
    for table in ("bodies", "joints", "couplers", "motors"):
        for name, row in tables[table].items():
            lines += ["", f"[{table}.{name}]"] + [f"{k} = {_fmt(v)}" for k, v in row.items()]
    return "\n".join(lines) + "\n"


def file_vs_design_mm(path: Path, dm: DesignedMechanism, actuators: list[str], lo: np.ndarray, hi: np.ndarray,
                      n: int = 20, seed: int = 0) -> float:
    """Largest distance (mm) between the written file's and the design's link motion (each link's frame origin
    and points 20 mm from it along each axis) at ``n`` random poses within the limits."""
    from models.mechanism import Mechanism

    written = Mechanism.load(path)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for p in rng.uniform(lo, hi, (n, len(actuators))):
        values = dict(zip(actuators, p, strict=True))
        a, b = written.transforms(values), dm.transforms(values)
        for link in dm.spec.links:
            o = dm.spec.bodies[link].origin
            pts = np.vstack([o, o + 0.02 * np.eye(3)])
            d = (pts @ a[link][:3, :3].T + a[link][:3, 3]) - (pts @ b[link][:3, :3].T + b[link][:3, 3])
            worst = max(worst, float(np.abs(d).max()))
    return worst * 1e3


def write_skin_sets(skin_dir: Path, node_sets: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Replace the attachment node sets of the skin mesh ``skin_dir/skin.vtu`` (nodes and tets unchanged) and read
    it back; returns each set's node count as written."""
    from offline.fem.mesh import load_mesh, save_mesh

    path = skin_dir / "skin.vtu"
    mesh = load_mesh(path)
    unknown = sorted(set(node_sets) - set(mesh.node_sets))
    if unknown:
        raise ValueError(f"{path}: no node set(s) {', '.join(unknown)} to replace")
    save_mesh(path, mesh.with_node_sets(**{n: np.asarray(v, dtype=np.int64) for n, v in node_sets.items()}))
    back = load_mesh(path)
    for n, v in node_sets.items():
        if not np.array_equal(np.sort(np.asarray(back.node_sets[n])), np.unique(np.asarray(v))):
            raise RuntimeError(f"{path}: node set {n} did not read back as written")
    return {n: len(back.node_sets[n]) for n in node_sets}


def write_head(config: str | Path, dm: DesignedMechanism, out: str | Path, note: str = "",
               map_samples: int = 300, node_sets: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Write the head folder ``out`` (config, mechanism, link map, skin, assets) for the design ``dm`` of the head
    ``config``, with the skin's attachment ``node_sets`` replaced where given (the ring step's sets); returns the
    checks (file vs design, map vs mechanism, in mm) and the files written."""
    from models.headspec import load_head
    from models.mechanism import Mechanism
    from offline.calibration.mechanism_fit import linkmap_from_mechanism

    config = Path(config)
    out = Path(out)
    head = load_head(config)
    src = config.resolve().parent
    out.mkdir(parents=True, exist_ok=True)
    for entry in COPIED:
        s = src / entry
        if s.is_dir():
            shutil.copytree(s, out / entry, dirs_exist_ok=True)
        elif s.is_file():
            shutil.copy2(s, out / entry)
    for key in ("predictor", "skin_guard"):
        p = head.path(key)
        if p is not None and Path(p).is_file():
            shutil.copy2(p, out / Path(p).name)
    written_sets = write_skin_sets(out / "skin", node_sets) if node_sets else None
    text = config.read_text()
    with atomic_path(out / "head.toml", suffix=".toml") as tmp:
        Path(tmp).write_text(f"# {note}\n" + text if note else text)
    mech_name = Path(head.path("mechanism")).name if head.path("mechanism") else "mechanism.toml"
    header = (f"The {head.name} head's mechanism after link-layout design (likeness offline clone "
              "--design-mechanism).\nNeutral configuration of the new layout (every motor at zero), head frame "
              "in metres; format: docs/mechanism.md.")
    with atomic_path(out / mech_name, suffix=".toml") as tmp:
        Path(tmp).write_text(mechanism_text(neutral_tables(dm), header))
    names = list(head.actuator_names)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    file_err = file_vs_design_mm(out / mech_name, dm, names, lo, hi)
    written = Mechanism.load(out / mech_name)
    prov = {"model": "mechanism", "mechanism": str(out / mech_name), "source": "layout design"}
    lm_name = Path(head.path("linkmap")).name if head.path("linkmap") else "linkmap.json"
    Pt = np.random.default_rng(1).uniform(lo, hi, (40, len(names)))
    truth = written.link_poses_many(names, Pt)  # every check pose at once
    tries = []
    for degree, more in MAP_TRIES:  # the cubic map, or a higher degree where a redesigned linkage bends more
        lm = linkmap_from_mechanism(written, head, samples=more * map_samples, degree=degree, provenance=prov)
        pred = lm.predict(Pt)
        map_err = max(float(np.linalg.norm(pred[n][:, :3] - truth[n][:, :3, 3], axis=1).max()) * 1e3
                      for n in written.links)
        tries.append({"degree": degree, "poses": more * map_samples, "map_vs_mechanism_max_mm": map_err})
        if map_err <= MAP_TOLERANCE_MM:
            break
    lm.save(out / lm_name)
    load_head(out / "head.toml")  # the head folder loads as the daemon loads it
    return {"head": str(out / "head.toml"), "mechanism": str(out / mech_name), "linkmap": str(out / lm_name),
            "file_vs_design_max_mm": file_err, "map_vs_mechanism_max_mm": map_err, "map_degree": lm.degree,
            "map_tries": tries, "skin_node_sets": written_sets,
            "map_within_tolerance": map_err <= MAP_TOLERANCE_MM, "map_tolerance_mm": MAP_TOLERANCE_MM}
