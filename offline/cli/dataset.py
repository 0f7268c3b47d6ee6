"""``likeness offline dataset``: simulate sampled poses of a head on an engine into a resumable dataset folder."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head and its skin, the sampling, the engine and the active-learning selection."""
    p.description = ("Sample actuator poses of a head (uniform or boundary values, group constraints honoured, "
                     "duplicates removed, seeded), solve each with the skin FEM through the link map m(p), "
                     "warm-started from the nearest solved pose, and store one file per pose plus a manifest. Rerun "
                     "the same command to resume after an interruption.")
    from offline.cli._common import add_skin_problem_arguments

    add_skin_problem_arguments(p)
    p.add_argument("--poses", type=int, required=True, help="number of distinct poses to sample")
    p.add_argument("--out", required=True, help="dataset folder (created, or resumed if it exists)")
    p.add_argument("--engine", default="local", help="local (default), dask-local or dask://HOST:PORT")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: CPU count)")
    p.add_argument("--threads-per-worker", type=int, default=1, help="solver threads in each worker")
    p.add_argument("--seed", type=int, default=0, help="sampling seed")
    p.add_argument("--boundary-prob", type=float, default=0.25,
                   help="probability that an actuator is set to a boundary value instead of a uniform one")
    p.add_argument("--range-fraction", type=float, default=1.0,
                   help="sample within this fraction of each actuator's span around neutral (default 1: full range); "
                   "the dataset and the predictor trained on it record the sampled range")
    p.add_argument("--max-poses", type=int, default=None, help="stop after solving this many new poses")
    p.add_argument("--start", choices=("nearest", "rest"), default="nearest",
                   help="where each pose's solve starts: the nearest pose solved so far (default; faster, but a skin "
                   "with several equilibria then takes whichever branch its neighbour was on, and that depends on "
                   "the order the workers finish in) or the skin at rest (every pose the equilibrium reached from "
                   "neutral: the same on every run)")
    p.add_argument("--select", choices=("genlal", "random"), default=None,
                   help="active learning: simulate only --budget of the --poses sampled candidates, chosen batch by "
                   "batch by a learned GEN-LAL policy (or at random, for comparison), retraining the predictor "
                   "between batches")
    p.add_argument("--budget", type=int, default=None, help="with --select: poses to simulate")
    p.add_argument("--batch", type=int, default=10, help="with --select: poses per batch (default 10)")
    p.add_argument("--init", type=int, default=None, help="with --select: random initial poses (default: --batch)")
    p.add_argument("--policy", default=None, help="with --select genlal: the policy file (likeness offline "
                   "al-benchmark writes DIR/policy.npz)")
    p.add_argument("--quiet", action="store_true", help="no progress line")


def run(args: argparse.Namespace) -> int:
    """Generate (or resume) the dataset and print its summary; exit 1 when poses failed, 130 when interrupted."""
    import json
    import signal
    import sys

    from offline.dataset.build import DatasetSettings, build_dataset

    settings = DatasetSettings(
        config=args.config, out=args.out, poses=args.poses, mesh=args.mesh, linkmap=args.linkmap,
        synthetic=args.synthetic, engine=args.engine, workers=args.workers,
        threads_per_worker=args.threads_per_worker, seed=args.seed, boundary_prob=args.boundary_prob,
        range_fraction=args.range_fraction, max_poses=args.max_poses, start=args.start,
        element_order=args.element_order,
        backend=args.backend, select=args.select, budget=args.budget, batch=args.batch, init=args.init,
        policy=args.policy)

    def _terminate(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)  # finish cleanly: in-flight poses are written, workers stop
    try:
        summary = build_dataset(settings, progress_stream=None if args.quiet else sys.stderr)
    except KeyboardInterrupt:
        print(f"\ninterrupted; rerun the same command to resume ({args.out})", file=sys.stderr)
        return 130
    print(json.dumps(summary, indent=1))
    return 0 if args.select is not None or summary["failed"] == 0 else 1
