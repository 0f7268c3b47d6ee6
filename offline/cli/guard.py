"""``likeness offline guard ...``: build and judge the skin-strain guard against the FEM.

- ``footprint``: write each surface triangle's distance to the rigid attachments (``[paths] skin_guard``).
- ``performances``: simulate the poses the head's performances command (FEM dataset folder, resumable).
- ``evaluate``: guard (full, reduced) vs the FEM measure on pose datasets; writes a JSON report with input hashes.
- ``refine``: the measure on the coarse skin and on its 1:8 refinement for a few poses (JSON report).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The four steps and their options."""
    gs = p.add_subparsers(dest="guard_command", metavar="STEP")
    p.set_defaults(guard_help=p.print_help)

    f = gs.add_parser("footprint", help="write each outer-surface triangle's distance to the rigid attachments")
    f.add_argument("--config", required=True, help="head spec TOML")
    f.add_argument("--mesh", required=True, help="skin mesh folder (skin.vtu + face_units.npz)")
    f.add_argument("--out", required=True, help="output .npz (name it in the head's [paths] skin_guard)")

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
    q.add_argument("--reuse", default=None, metavar="DATASET",
                   help="an earlier performances folder of the same skin problem: its solved poses at the same "
                   "values are copied, not solved again (after a new predictor only the blendshape clip's poses, "
                   "which come from the predictor's inverse, change)")

    e = gs.add_parser("evaluate", help="agreement of the guard with the FEM measure on pose datasets (JSON)")
    e.add_argument("--config", required=True)
    e.add_argument("--dataset", nargs="+", required=True,
                   help="pose datasets: folders (likeness offline dataset) or packs (.npz from "
                   "`likeness offline dataset-pack`, unpacked to a temporary folder and hash-checked); the report "
                   "names each as given")
    e.add_argument("--out", required=True, help="report .json")
    e.add_argument("--sample-out", help="also write a small test sample (.npz): evenly spaced poses of each dataset")
    e.add_argument("--sample-size", type=int, default=12, help="poses per dataset in --sample-out (default 12)")
    e.add_argument("--fresh", type=int, default=10000,
                   help="also compare the in-cycle check with the full measure on this many fresh seeded poses over "
                   "the full ranges (seed 1001) and as many within a quarter of each span around neutral (seed "
                   "1002); predictor only, no FEM (default 10000; 0: skip)")

    r = gs.add_parser("refine", help="the strain measure on the coarse skin and its 1:8 refinement (JSON)")
    r.add_argument("--config", required=True)
    r.add_argument("--mesh", required=True)
    r.add_argument("--dataset", required=True, help="take the poses from this pose dataset")
    r.add_argument("--poses", type=int, default=6, help="how many poses (spread over the measure's range)")
    r.add_argument("--backend", default="auto")
    r.add_argument("--out", required=True)


def run(args: argparse.Namespace) -> int:
    """Run the chosen step; without one, print the command's help (exit 2)."""
    steps = {"footprint": run_footprint, "performances": run_performances, "evaluate": run_evaluate,
             "refine": run_refine}
    if args.guard_command is None:
        args.guard_help()
        return 2
    return steps[args.guard_command](args)


def _command() -> str:
    """This command line, as reports record it."""
    return " ".join(["likeness", *sys.argv[1:]])


def run_footprint(args: argparse.Namespace) -> int:
    """Write the attachment distance file."""
    import numpy as np

    from models.headspec import load_head
    from offline.guard_reports import write_footprint

    rim, sets = write_footprint(load_head(args.config), Path(args.mesh), args.out, _command())
    print(f"{len(rim)} surface triangles, distance to attachments ({', '.join(sets)}): median "
          f"{np.median(rim) * 1e3:.1f} mm, min {rim.min() * 1e3:.1f} mm -> {args.out}")
    return 0


def run_performances(args: argparse.Namespace) -> int:
    """Sample the clips' poses and solve them with the FEM dataset tools."""
    import json

    from models.headspec import load_head
    from offline.guard_reports import solve_performances

    summary = solve_performances(load_head(args.config), args.config, args.mesh, args.clips, args.every, args.out,
                                 workers=args.workers, backend=args.backend, element_order=args.element_order,
                                 reuse=args.reuse)
    print(json.dumps(summary, indent=1))
    return 0 if summary["failed"] == 0 else 1


def run_evaluate(args: argparse.Namespace) -> int:
    """Write the agreement report (and the test sample)."""
    import tempfile

    from models.headspec import load_head
    from offline.cli._common import dataset_folder
    from offline.guard_reports import agreement, write_json, write_sample

    with tempfile.TemporaryDirectory(prefix="likeness-guard-") as tmp:
        folders = [dataset_folder(Path(d), Path(tmp) / str(i)) for i, d in enumerate(args.dataset)]
        report = agreement(load_head(args.config), args.config, folders, args.fresh, _command(), names=args.dataset)
        write_json(args.out, report)
        if args.sample_out:
            write_sample(args.sample_out, folders, args.sample_size, _command(), names=args.dataset)
    print(f"{report['poses']} poses: guard vs FEM {report['guard_vs_fem']:.4f}, reduced vs full "
          f"{report['reduced_vs_full']:.4f} -> {args.out}")
    return 0


def run_refine(args: argparse.Namespace) -> int:
    """Write the refinement report."""
    from models.headspec import load_head
    from offline.guard_reports import refinement, write_json

    report = refinement(load_head(args.config), args.mesh, args.dataset, args.poses, args.backend, _command())
    write_json(args.out, report)
    for row in report["poses"]:
        c, f = row["coarse"], row["fine"]
        fc = row["fine_on_coarse_triangles"]["measure"]
        print(f"measure coarse {c['measure'][0]:+.3f}/{c['measure'][1]:+.3f} fine {f['measure'][0]:+.3f}/"
              f"{f['measure'][1]:+.3f} fine solution on coarse triangles {fc[0]:+.3f}/{fc[1]:+.3f} | single "
              f"triangle max coarse {c['single_triangle_all'][1]:+.3f} fine {f['single_triangle_all'][1]:+.3f}")
    return 0
