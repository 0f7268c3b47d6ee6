"""The mesh refinement study, run resumably (what ``likeness offline refinement-study`` runs): representative poses
solved on successively finer skin meshes, their outer-surface displacements compared level to level.

Every solve is cached in ``OUT/solves/<level>/pose_<k>.npz`` (the pose, the outer-surface displacement at the
shipped mesh's outer vertices, convergence and time), so a killed run resumes where it stopped; ``OUT/report.json``
is rewritten atomically after every solve with what is known so far. The comparisons themselves are the pure
functions of :mod:`offline.refinement`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import UsageError
from models.headspec import HeadSpec, load_head
from offline.refinement import build_levels, compare_displacements, representative_poses, summarize
from offline.strain_eval import file_hash


@dataclass(frozen=True)
class StudySettings:
    """The study: the head, its skin mesh folder (default ``skin`` beside the config), the output folder, how many
    representative poses (``only``: just these labels), the levels compared in order (the first is ``L0``, the
    shipped mesh), the solver and the command line the report records."""

    config: str
    out: str
    mesh: str | None = None
    poses: int = 6
    seed: int = 0
    levels: tuple[str, ...] = ("L0", "P2", "L1")
    only: tuple[str, ...] | None = None
    backend: str = "auto"
    threads: int = 1
    command: str = "likeness offline refinement-study"


def shown(path: str | Path) -> str:
    """A path as the report shows it: relative to the working directory when inside it (portable reports)."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


def _atomic_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, path)


def _write_level_meshes(meshes: dict[str, Any], outer: np.ndarray, tris: np.ndarray, out: Path,
                        source_hash: str) -> dict[str, Path]:
    """Each level's mesh folder under ``out/meshes`` (reused when built from the same source mesh)."""
    from offline.fem import save_mesh

    folders = {}
    for name, mesh in meshes.items():
        folder = out / "meshes" / name
        stamp = folder / "source.json"
        if not (stamp.exists() and json.loads(stamp.read_text()).get("source_sha256") == source_hash
                and (folder / "skin.vtu").exists()):
            folder.mkdir(parents=True, exist_ok=True)
            save_mesh(folder / "skin.vtu", mesh)
            np.savez(folder / "face_units.npz", surface_nodes=outer, surface_triangles=tris)
            _atomic_json(stamp, {"source_sha256": source_hash, "level": name})
        folders[name] = folder
    return folders


def solve_cached(prob: Any, p: np.ndarray, rest: np.ndarray, path: Path) -> dict[str, Any]:
    """One pose on one level: from the cache when it holds this pose, else solved (1 load step, then 8 if the
    single step fails) and cached."""
    if path.exists():
        with np.load(path) as z:
            if np.array_equal(z["p"], p):
                return {"u": np.asarray(z["u"]), "converged": bool(z["converged"]), "iterations": int(z["iterations"]),
                        "load_steps": int(z["load_steps"]), "seconds": float(z["seconds"]), "cached": True}
    t0 = time.perf_counter()
    base = prob.options
    sol, steps = None, 1
    for steps in (1, 8):
        prob.options = dataclasses.replace(base, load_steps=steps)
        try:
            sol = prob.solve(p, None)
        finally:
            prob.options = base
        if sol.converged:
            break
    seconds = time.perf_counter() - t0
    u = np.asarray(sol.surface, dtype=np.float64) - rest if sol.converged else np.full_like(rest, np.nan)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, p=p, u=u, converged=sol.converged, iterations=sol.iterations, load_steps=steps, seconds=seconds)
    os.replace(tmp, path)
    return {"u": u, "converged": bool(sol.converged), "iterations": int(sol.iterations), "load_steps": steps,
            "seconds": seconds, "cached": False}


def _check(settings: StudySettings, mesh_dir: Path) -> None:
    """Refuse settings the study cannot run."""
    for f in ("skin.vtu", "face_units.npz"):
        if not (mesh_dir / f).is_file():
            raise UsageError(f"{mesh_dir}: no {f} (give the skin mesh folder with --mesh)")
    if len(set(settings.levels)) != len(settings.levels):
        raise UsageError(f"--levels names a level twice: {list(settings.levels)}")
    if settings.levels[0] != "L0":
        raise UsageError(f"--levels must start with L0 (the shipped mesh); got {settings.levels[0]}")
    if settings.poses < 1:
        raise UsageError(f"--poses must be positive, got {settings.poses}")


class _Study:
    """The study's state while it runs: its levels' problems, the poses and every solve known so far."""

    def __init__(self, settings: StudySettings, head: HeadSpec, mesh_dir: Path, t_start: float) -> None:
        from offline.dataset.fem_problem import FemSpec, material_fields
        from offline.fem import load_mesh

        self.settings, self.t_start = settings, t_start
        self.levels = list(settings.levels)
        out = Path(settings.out)
        material = head.skin_material()
        coarse = load_mesh(mesh_dir / "skin.vtu")
        with np.load(mesh_dir / "face_units.npz") as z:
            outer = np.asarray(z["surface_nodes"], dtype=np.int64)
            tris = np.asarray(z["surface_triangles"], dtype=np.int64)
        source_hash = file_hash(mesh_dir / "skin.vtu")
        try:
            meshes = build_levels(coarse, outer, tris, self.levels)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
        folders = _write_level_meshes(meshes, outer, tris, out, source_hash)
        linkmap = head.path("linkmap")
        self.inputs = {"config": shown(settings.config), "config_sha256": file_hash(settings.config),
                       "mesh": shown(mesh_dir / "skin.vtu"), "mesh_sha256": source_hash,
                       "face_units_sha256": file_hash(mesh_dir / "face_units.npz"),
                       "linkmap": shown(linkmap), "linkmap_sha256": file_hash(linkmap)}
        if material is not None and material.source:
            self.inputs["material_source"] = material.source
        poses, labels = representative_poses(head, settings.poses, settings.seed)
        self.index = list(range(len(poses)))  # each pose's number among all --poses (names its cache file)
        if settings.only:
            missing = sorted(set(settings.only) - set(labels))
            if missing:
                raise UsageError(f"--only names poses not among the {settings.poses} poses: {missing} "
                                 f"(known: {labels})")
            keep = [k for k, lab in enumerate(labels) if lab in settings.only]
            poses, labels, self.index = poses[keep], [labels[k] for k in keep], keep
        self.poses, self.labels = poses, labels
        self.rest = np.asarray(coarse.nodes)[outer]
        self.problems: dict[str, Any] = {}
        self.levels_info: dict[str, Any] = {}
        for name in self.levels:
            spec = FemSpec(config=str(settings.config), mesh=str(folders[name]), linkmap=str(linkmap),
                           backend=settings.backend, threads=settings.threads, **material_fields(material))
            prob = spec.build()
            if name != "L0":  # one link frame alignment for every level (the node sets' centroids shift slightly)
                prob.frame_offset = self.problems["L0"].frame_offset
            self.problems[name] = prob
            m = meshes[name]
            self.levels_info[name] = {"element_order": int(m.order), "elements": int(m.n_tets),
                                      "nodes": int(m.n_nodes), "dofs": 3 * int(m.n_nodes),
                                      "mesh_sha256": file_hash(folders[name] / "skin.vtu")}
        self.region_names, self.region_labels = self.problems["L0"].surface_regions()
        self.levels_info[self.levels[0]]["material"] = self.problems[self.levels[0]].spec.skin_material().as_dict()
        self.solves: dict[str, list[dict[str, Any] | None]] = {n: [None] * len(poses) for n in self.levels}
        self.disp: dict[str, list[np.ndarray | None]] = {n: [None] * len(poses) for n in self.levels}
        self.study_settings = {
            "poses": settings.poses, "only": list(settings.only) if settings.only else settings.only,
            "seed": settings.seed, "levels": list(self.levels), "backend": settings.backend,
            "threads": settings.threads, "load_steps": "1, else 8",
            "compared_at": "the shipped mesh's outer-surface vertices (kept first, in order, by every level)",
            "outer_vertices": len(outer)}
        self.pose_rows = [{"label": lab, "p_si": [float(x) for x in p]} for lab, p in zip(labels, poses, strict=True)]

    def report(self) -> dict[str, Any]:
        """The report of what is known so far."""
        pairs: dict[str, list[dict[str, Any] | None]] = {}
        for a, b in zip(self.levels[:-1], self.levels[1:], strict=True):
            rows: list[dict[str, Any] | None] = []
            for k in range(len(self.poses)):
                ua, ub = self.disp[a][k], self.disp[b][k]
                sa, sb = self.solves[a][k], self.solves[b][k]
                ok = ua is not None and ub is not None and sa is not None and sb is not None \
                    and sa["converged"] and sb["converged"]
                rows.append({"pose": self.labels[k],
                             **compare_displacements(ua, ub, self.region_names, self.region_labels)} if ok else None)
            pairs[f"{a}->{b}"] = rows
        return {"command": self.settings.command, "inputs": self.inputs, "settings": self.study_settings,
                "levels": self.levels_info,
                "regions": {"names": list(self.region_names),
                            "vertices": [int((self.region_labels == r).sum()) for r in range(len(self.region_names))]},
                "poses": self.pose_rows,
                "solves": {n: [None if s is None else {k: v for k, v in s.items() if k != "u"} for s in self.solves[n]]
                           for n in self.levels},
                "pairs": pairs, "summary": summarize(pairs),
                "complete": all(s is not None for n in self.levels for s in self.solves[n]),
                "seconds": round(time.perf_counter() - self.t_start, 2)}


def run_study(settings: StudySettings, say: Callable[[str], None] = lambda line: print(line, flush=True)
              ) -> dict[str, Any]:
    """Solve every pose on every level (cached solves reused), rewriting ``OUT/report.json`` after each; ``say``
    hears one line per solve. Returns the final report."""
    t_start = time.perf_counter()
    head = load_head(settings.config)
    mesh_dir = Path(settings.mesh) if settings.mesh else Path(settings.config).resolve().parent / "skin"
    _check(settings, mesh_dir)
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    study = _Study(settings, head, mesh_dir, t_start)
    total = len(study.levels) * len(study.poses)
    done = 0
    for name in study.levels:
        for k, p in enumerate(study.poses):
            res = solve_cached(study.problems[name], p, study.rest,
                               out / "solves" / name / f"pose_{study.index[k]:03d}.npz")
            study.solves[name][k] = res
            study.disp[name][k] = res["u"] if res["converged"] else None
            done += 1
            say(f"[{done}/{total}] {name} {study.labels[k]}: {'converged' if res['converged'] else 'NOT CONVERGED'} "
                f"{res['iterations']} it, {res['load_steps']} step(s), {res['seconds']:.1f} s"
                f"{' (cached)' if res['cached'] else ''}")
            _atomic_json(out / "report.json", study.report())
    doc = study.report()
    _atomic_json(out / "report.json", doc)
    return doc
