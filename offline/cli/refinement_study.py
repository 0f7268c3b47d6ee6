"""``likeness offline refinement-study``: solve representative poses on successively finer skin meshes.

Every solve is cached in ``DIR/solves/<level>/pose_<k>.npz`` (the pose, the outer-surface displacement at the
shipped mesh's outer vertices, convergence and time), so a killed run resumes where it stopped; ``DIR/report.json``
is rewritten atomically after every solve with what is known so far.
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head, its mesh, the output folder, the poses, the levels and the solver."""
    from offline.refinement import LEVELS

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


def run(args: argparse.Namespace) -> int:
    """Solve, compare and write the report; print each level pair's summary."""
    import sys
    from pathlib import Path

    from offline.refinement_study import StudySettings, run_study

    argv = sys.argv[3:] if sys.argv[1:3] == ["offline", "refinement-study"] else sys.argv[1:]
    settings = StudySettings(config=args.config, out=args.out, mesh=args.mesh, poses=args.poses, seed=args.seed,
                             levels=tuple(args.levels), only=tuple(args.only) if args.only else None,
                             backend=args.backend, threads=args.threads,
                             command="likeness offline refinement-study " + " ".join(argv))
    doc = run_study(settings)
    for pair, s in doc["summary"].items():
        print(f"{pair}: mean {s['mean_m'] * 1e3:.3f} mm, p99 {s['p99_max_m'] * 1e3:.3f} mm, max "
              f"{s['max_m'] * 1e3:.3f} mm ({s['max_pose']}, {s['max_region']}), relative mean {s['relative_mean']}")
    print(f"wrote {Path(args.out) / 'report.json'}")
    return 0
