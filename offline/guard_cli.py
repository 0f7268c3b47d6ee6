"""``likeness offline guard ...``: build and judge the skin-strain guard against the FEM.

- ``footprint``: write each surface triangle's distance to the rigid attachments (``[paths] skin_guard``).
- ``performances``: simulate the poses the head's performances command (FEM dataset folder, resumable).
- ``evaluate``: guard (full, reduced) vs the FEM measure on pose datasets; writes a JSON report with input hashes.
- ``refine``: the measure on the coarse skin and on its 1:8 refinement for a few poses (JSON report).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from models.atomic import write_bytes


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``guard`` tool and its subcommands."""
    p = sub.add_parser("guard", help="skin-strain guard: footprint, FEM poses, agreement and refinement reports")
    gs = p.add_subparsers(dest="guard_command", metavar="STEP")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    f = gs.add_parser("footprint", help="write each outer-surface triangle's distance to the rigid attachments")
    f.add_argument("--config", required=True, help="head spec TOML")
    f.add_argument("--mesh", required=True, help="skin mesh folder (skin.vtu + face_units.npz)")
    f.add_argument("--out", required=True, help="output .npz (name it in the head's [paths] skin_guard)")
    f.set_defaults(func=run_footprint)

    q = gs.add_parser("performances", help="FEM-solve the poses of performance clips into a pose dataset")
    q.add_argument("--config", required=True)
    q.add_argument("--mesh", required=True)
    q.add_argument("--clips", nargs="+", required=True, help="performance clip files (.json/.csv)")
    q.add_argument("--every", type=float, default=0.1, help="seconds between sampled poses (default 0.1)")
    q.add_argument("--out", required=True, help="dataset folder (resumable)")
    q.add_argument("--workers", type=int, default=1)
    q.add_argument("--backend", default="auto")
    q.add_argument("--element-order", type=int, choices=(1, 2), default=1,
                   help="1: the mesh's linear tets; 2: the same tets quadratic (as the predictor's dataset)")
    q.set_defaults(func=run_performances)

    e = gs.add_parser("evaluate", help="agreement of the guard with the FEM measure on pose datasets (JSON)")
    e.add_argument("--config", required=True)
    e.add_argument("--dataset", nargs="+", required=True, help="pose dataset folders (likeness offline dataset)")
    e.add_argument("--out", required=True, help="report .json")
    e.add_argument("--sample-out", help="also write a small test sample (.npz): evenly spaced poses of each dataset")
    e.add_argument("--sample-size", type=int, default=12, help="poses per dataset in --sample-out (default 12)")
    e.add_argument("--fresh", type=int, default=10000,
                   help="also compare the in-cycle check with the full measure on this many fresh seeded poses over "
                   "the full ranges (seed 1001) and as many within a quarter of each span around neutral (seed "
                   "1002); predictor only, no FEM (default 10000; 0: skip)")
    e.set_defaults(func=run_evaluate)

    r = gs.add_parser("refine", help="the strain measure on the coarse skin and its 1:8 refinement (JSON)")
    r.add_argument("--config", required=True)
    r.add_argument("--mesh", required=True)
    r.add_argument("--dataset", required=True, help="take the poses from this pose dataset")
    r.add_argument("--poses", type=int, default=6, help="how many poses (spread over the measure's range)")
    r.add_argument("--backend", default="auto")
    r.add_argument("--out", required=True)
    r.set_defaults(func=run_refine)


def _head(path: str) -> Any:
    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head

    try:
        return load_head(path)
    except SpecError as exc:
        raise CliError(str(exc)) from exc


def _load_surface(mesh_dir: Path) -> tuple[Any, Any]:
    import numpy as np

    from likeness.cli import CliError
    from offline.fem import load_mesh

    if not (mesh_dir / "skin.vtu").is_file() or not (mesh_dir / "face_units.npz").is_file():
        raise CliError(f"{mesh_dir}: needs skin.vtu and face_units.npz (likeness offline mesh)")
    mesh = load_mesh(mesh_dir / "skin.vtu")
    with np.load(mesh_dir / "face_units.npz") as z:
        triangles = np.asarray(z["surface_triangles"], dtype=np.int64)
    return mesh, triangles


def run_footprint(args: argparse.Namespace) -> int:
    """Write the attachment distance file."""
    import numpy as np

    from models.strain_guard import save_footprint
    from offline.strain_eval import attachment_distance, file_hash

    head = _head(args.config)
    mesh_dir = Path(args.mesh)
    mesh, triangles = _load_surface(mesh_dir)
    rim, sets = attachment_distance(head, mesh, triangles)
    save_footprint(args.out, rim, sets, {
        "command": " ".join(["likeness", *sys.argv[1:]]), "mesh_sha256": file_hash(mesh_dir / "skin.vtu"),
        "surface_sha256": file_hash(mesh_dir / "face_units.npz"),
        "rule": "centroid distance to boundary triangles/edges with all nodes in one attachment set"})
    print(f"{len(rim)} surface triangles, distance to attachments ({', '.join(sets)}): median "
          f"{np.median(rim) * 1e3:.1f} mm, min {rim.min() * 1e3:.1f} mm -> {args.out}")
    return 0


def run_performances(args: argparse.Namespace) -> int:
    """Sample the clips' poses and solve them with the FEM dataset tools."""
    import numpy as np

    from offline.dataset.fem_problem import FemSpec, material_fields
    from offline.dataset.generate import generate_dataset
    from offline.engine import make_engine
    from offline.strain_eval import performance_poses

    head = _head(args.config)
    poses, labels = performance_poses(head, args.clips, every_s=args.every)
    _, idx = np.unique(np.round(poses, 9), axis=0, return_index=True)
    idx = np.sort(idx)
    poses = poses[idx]
    spec = FemSpec(config=str(args.config), mesh=str(args.mesh), linkmap=str(head.path("linkmap")),
                   backend=args.backend, element_order=args.element_order,
                   **material_fields(head.skin_material()))
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    with make_engine("local", args.workers, 1) as engine:
        summary = generate_dataset(args.out, spec, poses, head=head.name, names=head.actuator_names, units=units,
                                   lo=lo, hi=hi, engine=engine, seed=0,
                                   sampling={"performances": [str(c) for c in args.clips], "every_s": args.every,
                                             "labels": [labels[i] for i in idx]},
                                   rest_pose=head.neutral_pose)
    print(json.dumps(summary, indent=1))
    return 0 if summary["failed"] == 0 else 1


def run_evaluate(args: argparse.Namespace) -> int:
    """Write the agreement report."""
    from likeness.cli import CliError
    from models.strain_guard import StrainGuard
    from offline.strain_eval import agreement_report, file_hash, reduced_agreement

    head = _head(args.config)
    if args.fresh < 0:
        raise CliError(f"--fresh must be zero or positive, got {args.fresh}")
    t0 = time.perf_counter()
    guard = StrainGuard.for_head(head)
    if guard is None:
        raise CliError(f"{args.config}: the head names no existing predictor")
    fp = head.path("skin_guard")
    report = agreement_report(guard, args.dataset)
    other = "neutral" if guard.reference_kind == "rest" else "rest"
    alt = StrainGuard(guard.predictor, guard.neutral, guard.strain_range, guard.surface.rim_distance,
                      guard.surface.radius, guard.surface.band, samples=200, names=guard.names, reference=other)
    alt_report = agreement_report(alt, args.dataset)
    report["reference_comparison"] = {
        ref: {"guard_vs_fem": rep["guard_vs_fem"],
              "median_abs_error_vs_fem": {k: d["median_abs_error_vs_fem"] for k, d in rep["per_dataset"].items()}}
        for ref, rep in ((guard.reference_kind, report), (other, alt_report))}
    if args.fresh:
        report["reduced_vs_full_fresh"] = [reduced_agreement(guard, head, args.fresh, 1001, 1.0),
                                           reduced_agreement(guard, head, args.fresh, 1002, 0.25)]
    cal = guard.calibration
    report.update({
        "command": " ".join(["likeness", *sys.argv[1:]]),
        "inputs": {"config": {"path": str(head.source), "sha256": file_hash(head.source)},
                   "predictor": {"path": str(guard.predictor.path), "sha256": file_hash(guard.predictor.path)},
                   "skin_guard": {"path": str(fp), "sha256": file_hash(fp)} if fp is not None else None},
        "settings": {"strain_range": list(guard.strain_range), "radius_m": guard.surface.radius,
                     "band_m": guard.surface.band, "reference": guard.reference_kind,
                     "kept_area_fraction": guard.surface.kept_area_fraction},
        "reduced": {"patches": cal.patches, "patches_total": cal.patches_total, "vertices": cal.vertices,
                    "calibration_samples": cal.samples, "calibration_seed": cal.seed,
                    "calibration_agreement": cal.agreement},
        "seconds": time.perf_counter() - t0,
    })
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_bytes(Path(args.out), (json.dumps(report, indent=1) + "\n").encode())
    if args.sample_out:
        write_sample(args.sample_out, args.dataset, args.sample_size)
    print(f"{report['poses']} poses: guard vs FEM {report['guard_vs_fem']:.4f}, reduced vs full "
          f"{report['reduced_vs_full']:.4f} -> {args.out}")
    return 0


def run_refine(args: argparse.Namespace) -> int:
    """Write the refinement report."""
    import numpy as np

    from models.strain_guard import StrainGuard
    from offline.dataset.store import PoseDataset
    from offline.strain_eval import file_hash, refinement_study

    head = _head(args.config)
    guard = StrainGuard.for_head(head)
    ds = PoseDataset(args.dataset)
    idx = ds.usable
    full = guard.full_batch(ds.actuators[idx]) if guard is not None else np.zeros((len(idx), 2))
    order = idx[np.argsort(full[:, 1])]
    pick = order[np.linspace(0, len(order) - 1, args.poses).round().astype(int)]
    t0 = time.perf_counter()
    radius = guard.surface.radius if guard is not None else 0.008
    band = guard.surface.band if guard is not None else 0.005
    report = refinement_study(head, args.mesh, ds.actuators[pick], radius, band, backend=args.backend)
    report.update({"command": " ".join(["likeness", *sys.argv[1:]]), "dataset": str(args.dataset),
                   "dataset_indices": [int(i) for i in pick],
                   "mesh_sha256": file_hash(Path(args.mesh) / "skin.vtu"), "seconds": time.perf_counter() - t0})
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_bytes(Path(args.out), (json.dumps(report, indent=1) + "\n").encode())
    for row in report["poses"]:
        c, f = row["coarse"], row["fine"]
        fc = row["fine_on_coarse_triangles"]["measure"]
        print(f"measure coarse {c['measure'][0]:+.3f}/{c['measure'][1]:+.3f} fine {f['measure'][0]:+.3f}/"
              f"{f['measure'][1]:+.3f} fine solution on coarse triangles {fc[0]:+.3f}/{fc[1]:+.3f} | single "
              f"triangle max coarse {c['single_triangle_all'][1]:+.3f} fine {f['single_triangle_all'][1]:+.3f}")
    return 0


def write_sample(path: str, datasets: list[str], per_dataset: int) -> None:
    """Evenly spaced converged poses of each dataset: p, surface offsets (float32), base surface, faces."""
    import numpy as np

    from offline.dataset.store import PoseDataset

    P, off, src = [], [], []
    base = faces = None
    for root in datasets:
        ds = PoseDataset(root)
        idx = ds.usable
        pick = idx[np.linspace(0, len(idx) - 1, min(per_dataset, len(idx))).round().astype(int)]
        P.append(ds.actuators[pick])
        off.append(np.asarray(ds.offsets[pick], dtype=np.float32))
        src += [f"{Path(root).name}#{i}" for i in pick]
        base, faces = ds.base_vertices, ds.faces
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, p=np.concatenate(P), offsets=np.concatenate(off), base=base, faces=faces,
                        source=np.array(src), command=np.array(" ".join(["likeness", *sys.argv[1:]])))
    write_bytes(Path(path), buf.getvalue())
