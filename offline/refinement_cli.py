"""``likeness offline refinement-study``: solve representative poses on successively finer skin meshes.

Every solve is cached in ``DIR/solves/<level>/pose_<k>.npz`` (the pose, the outer-surface displacement at the
shipped mesh's outer vertices, convergence and time), so a killed run resumes where it stopped; ``DIR/report.json``
is rewritten atomically after every solve with what is known so far.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``refinement-study`` tool."""
    from offline.refinement import LEVELS

    p = sub.add_parser("refinement-study",
                       help="outer-surface displacement change of representative poses between mesh refinements")
    p.add_argument("--config", required=True, help="head spec TOML")
    p.add_argument("--mesh", help="skin mesh folder (skin.vtu + face_units.npz; default: 'skin' beside the config)")
    p.add_argument("--out", required=True, help="output folder (report.json, meshes, cached solves; resumable)")
    p.add_argument("--poses", type=int, default=6,
                   help="poses: neutral, jaw open, left and right smile, then random ones (default 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random poses (default 0)")
    p.add_argument("--levels", nargs="+", default=["L0", "P2", "L1"],
                   help=f"levels to solve, compared in the order given (known: {' '.join(LEVELS)}; default L0 P2 L1)")
    p.add_argument("--only", nargs="+", metavar="LABEL",
                   help="solve only these of the poses (labels such as smile_l, random_0): for costly levels")
    p.add_argument("--backend", default="auto", help="sparse solver backend (default auto)")
    p.add_argument("--threads", type=int, default=1, help="FEM kernel threads (default 1)")
    p.set_defaults(func=run)


def _shown(path: str | Path) -> str:
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


def _solve_cached(prob: Any, p: np.ndarray, rest: np.ndarray, path: Path) -> dict[str, Any]:
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


def run(args: argparse.Namespace) -> int:
    """Solve, compare and write the report."""
    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head
    from offline.dataset.fem_problem import FemSpec, material_fields
    from offline.fem import load_mesh
    from offline.refinement import build_levels, compare_displacements, representative_poses, summarize
    from offline.strain_eval import file_hash

    t_start = time.perf_counter()
    try:
        head = load_head(args.config)
        material = head.skin_material()
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    mesh_dir = Path(args.mesh) if args.mesh else Path(args.config).resolve().parent / "skin"
    for f in ("skin.vtu", "face_units.npz"):
        if not (mesh_dir / f).is_file():
            raise CliError(f"{mesh_dir}: no {f} (give the skin mesh folder with --mesh)")
    if len(set(args.levels)) != len(args.levels):
        raise CliError(f"--levels names a level twice: {args.levels}")
    if args.levels[0] != "L0":
        raise CliError(f"--levels must start with L0 (the shipped mesh); got {args.levels[0]}")
    if args.poses < 1:
        raise CliError(f"--poses must be positive, got {args.poses}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    coarse = load_mesh(mesh_dir / "skin.vtu")
    with np.load(mesh_dir / "face_units.npz") as z:
        outer = np.asarray(z["surface_nodes"], dtype=np.int64)
        tris = np.asarray(z["surface_triangles"], dtype=np.int64)
    source_hash = file_hash(mesh_dir / "skin.vtu")
    try:
        meshes = build_levels(coarse, outer, tris, args.levels)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    folders = _write_level_meshes(meshes, outer, tris, out, source_hash)
    linkmap = head.path("linkmap")
    inputs = {"config": _shown(args.config), "config_sha256": file_hash(args.config),
              "mesh": _shown(mesh_dir / "skin.vtu"), "mesh_sha256": source_hash,
              "face_units_sha256": file_hash(mesh_dir / "face_units.npz"),
              "linkmap": _shown(linkmap), "linkmap_sha256": file_hash(linkmap)}
    if material is not None and material.source:
        inputs["material_source"] = material.source

    poses, labels = representative_poses(head, args.poses, args.seed)
    index = list(range(len(poses)))  # each pose's number among all --poses (names its cache file)
    if args.only:
        missing = sorted(set(args.only) - set(labels))
        if missing:
            raise CliError(f"--only names poses not among the {args.poses} poses: {missing} (known: {labels})")
        keep = [k for k, lab in enumerate(labels) if lab in args.only]
        poses, labels, index = poses[keep], [labels[k] for k in keep], keep
    rest = np.asarray(coarse.nodes)[outer]
    problems: dict[str, Any] = {}
    levels_info: dict[str, Any] = {}
    for name in args.levels:
        spec = FemSpec(config=str(args.config), mesh=str(folders[name]), linkmap=str(linkmap), backend=args.backend,
                       threads=args.threads, **material_fields(material))
        prob = spec.build()
        if name != "L0":  # one link frame alignment for every level (the node sets' centroids shift slightly)
            prob.frame_offset = problems["L0"].frame_offset
        problems[name] = prob
        m = meshes[name]
        levels_info[name] = {"element_order": int(m.order), "elements": int(m.n_tets), "nodes": int(m.n_nodes),
                             "dofs": 3 * int(m.n_nodes), "mesh_sha256": file_hash(folders[name] / "skin.vtu")}
    region_names, region_labels = problems["L0"].surface_regions()
    if len(problems) and args.levels:
        levels_info[args.levels[0]]["material"] = problems[args.levels[0]].spec.skin_material().as_dict()

    solves: dict[str, list[dict[str, Any] | None]] = {n: [None] * len(poses) for n in args.levels}
    disp: dict[str, list[np.ndarray | None]] = {n: [None] * len(poses) for n in args.levels}
    settings = {"poses": args.poses, "only": args.only, "seed": args.seed, "levels": list(args.levels),
                "backend": args.backend, "threads": args.threads, "load_steps": "1, else 8",
                "compared_at": "the shipped mesh's outer-surface vertices (kept first, in order, by every level)",
                "outer_vertices": len(outer)}
    pose_rows = [{"label": lab, "p_si": [float(x) for x in p]} for lab, p in zip(labels, poses, strict=True)]

    def report() -> dict[str, Any]:
        pairs: dict[str, list[dict[str, Any] | None]] = {}
        for a, b in zip(args.levels[:-1], args.levels[1:], strict=True):
            rows = []
            for k in range(len(poses)):
                ua, ub = disp[a][k], disp[b][k]
                ok = (ua is not None and ub is not None and solves[a][k]["converged"]
                      and solves[b][k]["converged"])
                rows.append({"pose": labels[k], **compare_displacements(ua, ub, region_names, region_labels)}
                            if ok else None)
            pairs[f"{a}->{b}"] = rows
        return {"command": "likeness offline refinement-study " + " ".join(sys.argv[3:] if sys.argv[1:3] == [
                    "offline", "refinement-study"] else sys.argv[1:]),
                "inputs": inputs, "settings": settings, "levels": levels_info,
                "regions": {"names": list(region_names),
                            "vertices": [int((region_labels == r).sum()) for r in range(len(region_names))]},
                "poses": pose_rows, "solves": {n: [None if s is None else {k: v for k, v in s.items() if k != "u"}
                                                   for s in solves[n]] for n in args.levels},
                "pairs": pairs, "summary": summarize(pairs),
                "complete": all(s is not None for n in args.levels for s in solves[n]),
                "seconds": round(time.perf_counter() - t_start, 2)}

    total = len(args.levels) * len(poses)
    done = 0
    for name in args.levels:
        for k, p in enumerate(poses):
            res = _solve_cached(problems[name], p, rest, out / "solves" / name / f"pose_{index[k]:03d}.npz")
            solves[name][k] = res
            disp[name][k] = res["u"] if res["converged"] else None
            done += 1
            print(f"[{done}/{total}] {name} {labels[k]}: {'converged' if res['converged'] else 'NOT CONVERGED'} "
                  f"{res['iterations']} it, {res['load_steps']} step(s), {res['seconds']:.1f} s"
                  f"{' (cached)' if res['cached'] else ''}", flush=True)
            _atomic_json(out / "report.json", report())
    doc = report()
    _atomic_json(out / "report.json", doc)
    for pair, s in doc["summary"].items():
        print(f"{pair}: mean {s['mean_m'] * 1e3:.3f} mm, p99 {s['p99_max_m'] * 1e3:.3f} mm, max "
              f"{s['max_m'] * 1e3:.3f} mm ({s['max_pose']}, {s['max_region']}), relative mean {s['relative_mean']}")
    print(f"wrote {out / 'report.json'}")
    return 0
