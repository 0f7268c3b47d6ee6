"""``likeness offline al-benchmark``: GEN-LAL against the baselines on one pool, budget and set of seeds."""

from __future__ import annotations

import argparse

QUICK = {"pool": {"poses": 150, "seed": 11, "synthetic": True, "synthetic_grid": 12},
         "bench": {"init": 6, "batch": 6, "budget": 36, "seeds": 2},
         "policy": {"n_runs": 2, "init": 6, "batch": 8, "budget": 30, "candidates_per_step": 5, "pseudo_test": 20,
                    "epochs": 8},
         "learner": {"iterations": 25, "fine_tune_iterations": 4}}
#: The FEM pool shipped beside a head's config (``likeness offline dataset-pack`` of the default pool's dataset).
PACK_NAME = "al_pool.npz"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``al-benchmark`` tool."""
    p = sub.add_parser("al-benchmark", help="benchmark GEN-LAL active learning against baselines (resumable)",
                       description="Generate (or resume) a labelled pose dataset of the head, split it into a pool, "
                       "a policy pool and a test set, learn the GEN-LAL policy on the policy pool, then run GEN-LAL, "
                       "random, greedy fully informed, space-filling, committee variance and bmdal-reg's LCMD and "
                       "MaxDist over several seeds with the same budget, and write DIR/report.json and "
                       "DIR/al_benchmark.png. Rerun the same command to resume after an interruption.")
    p.add_argument("--config", required=True, help="head spec TOML (e.g. heads/sample/head.toml)")
    p.add_argument("--out", required=True, help="output folder (created, or resumed)")
    p.add_argument("--quick", action="store_true", help="analytic skin, small pool and budget (tests; seconds)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per method (default 3; quick 2)")
    p.add_argument("--mesh", default=None, help="skin mesh folder (default: skin/ beside the config)")
    p.add_argument("--pool", default=None, help="use this consolidated pose dataset instead of DIR/pool")
    p.add_argument("--pool-pack", default=None,
                   help=f"unpack this dataset pack into DIR/pool instead of simulating the FEM pool (default: "
                   f"{PACK_NAME} beside the config when it exists and matches the default pool)")
    p.add_argument("--simulate-pool", action="store_true",
                   help=f"simulate the FEM pool even when a pack ({PACK_NAME}) is shipped beside the config")
    p.add_argument("--policy", default=None, help="use this learned policy file instead of learning one")
    p.add_argument("--methods", default=None, help="comma-separated subset of the methods (default: all)")
    p.add_argument("--init", type=int, default=None, help="random initial poses per seed (default 10; quick 6)")
    p.add_argument("--batch", type=int, default=None, help="poses per batch (default 10; quick 6)")
    p.add_argument("--budget", type=int, default=None, help="labelled poses at the end (default 100; quick 36)")
    p.add_argument("--policy-runs", type=int, default=None, help="simulated AL runs the policy learns from "
                   "(default 6; quick 2)")
    p.add_argument("--policy-fraction", type=float, default=0.35,
                   help="share of the dataset's train and validation poses set aside as the policy pool (default 0.35)")
    p.add_argument("--synthetic", action="store_true",
                   help="analytic sheet instead of the FEM at the default sizes (quick implies it)")
    p.add_argument("--sheet-grid", type=int, default=None,
                   help="analytic sheet: vertices per side (default 14; quick 12) - a finer or coarser 'mesh'")
    p.add_argument("--sheet-stiffening", type=float, default=None,
                   help="analytic sheet: cubic stiffening of its 'material' (default 2e4)")
    p.add_argument("--skin-nu", type=float, default=None,
                   help="simulate the FEM pool with this Poisson ratio instead of the head's skin material's "
                   "(a changed skin: with --policy, measures a policy learned on one skin selecting for another)")
    p.add_argument("--workers", type=int, default=None, help="FEM worker processes for the pool (default: CPUs)")
    p.add_argument("--engine", default="local", help="engine for the pool's FEM poses: local, dask-local, dask://")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Pool, policy, benchmark, report and figure."""
    import sys
    import time
    from dataclasses import replace
    from pathlib import Path

    import torch

    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head
    from offline.active.data import PoolSettings, ensure_pool
    from offline.active.learner import LearnerConfig
    from offline.active.policy import PolicySettings
    from offline.active.report import run_and_report
    from offline.active.selectors import METHODS

    torch.set_num_threads(1)
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:7.0f} s] {msg}", file=sys.stderr, flush=True)

    try:
        head = load_head(args.config)
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    methods = tuple(m.strip() for m in args.methods.split(",")) if args.methods else METHODS
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise CliError(f"--methods: unknown {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    if args.seeds is not None and args.seeds < 1:
        raise CliError(f"--seeds must be positive, got {args.seeds}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from offline.active.benchmark import BenchmarkSettings

    if args.quick:
        pool_settings = PoolSettings(**QUICK["pool"])
        bench = BenchmarkSettings(**{**QUICK["bench"], **({"seeds": args.seeds} if args.seeds else {})})
        policy = PolicySettings(**QUICK["policy"])
        cfg = LearnerConfig(**QUICK["learner"])
    else:
        pool_settings = PoolSettings()
        bench = BenchmarkSettings(**({"seeds": args.seeds} if args.seeds else {}))
        policy = PolicySettings()
        cfg = LearnerConfig()
    overrides = {k: v for k, v in (("init", args.init), ("batch", args.batch), ("budget", args.budget))
                 if v is not None}
    if any(v < 1 for v in overrides.values()):
        raise CliError(f"--init, --batch and --budget must be positive, got {overrides}")
    if overrides:
        bench = replace(bench, **overrides)
        policy = replace(policy, init=bench.init, batch=bench.batch, budget=bench.budget)
    if args.policy_runs is not None:
        if args.policy_runs < 1:
            raise CliError(f"--policy-runs must be positive, got {args.policy_runs}")
        policy = replace(policy, n_runs=args.policy_runs)
    sheet = {k: v for k, v in (("synthetic_grid", args.sheet_grid), ("synthetic_stiffening", args.sheet_stiffening))
             if v is not None}
    if args.synthetic or sheet:
        pool_settings = replace(pool_settings, synthetic=True, **sheet)
    if args.skin_nu is not None:
        if not 0.0 < args.skin_nu < 0.5:
            raise CliError(f"--skin-nu must lie in (0, 0.5), got {args.skin_nu}")
        if pool_settings.synthetic:
            raise CliError("--skin-nu changes the FEM skin; the analytic sheet (--quick, --synthetic) has none")
        pool_settings = replace(pool_settings, nu=args.skin_nu)
    pool_dir = Path(args.pool) if args.pool else out / "pool"
    pack = _pool_pack(args, pool_settings)
    if args.pool is None and pack is not None:
        from offline.dataset.pack import unpack_dataset

        log(f"pool: unpacking {pack} into {pool_dir} (made by: {_pack_made_by(pack)})")
        try:
            unpack_dataset(pack, pool_dir)
        except (SpecError, OSError, ValueError) as exc:
            raise CliError(str(exc)) from exc
    elif args.pool is None:
        mesh = args.mesh or str(Path(args.config).parent / "skin")
        log(f"pool: {pool_settings.poses} {'analytic' if pool_settings.synthetic else 'FEM'} poses into {pool_dir} "
            "(resumes if present)")
        try:
            summary = ensure_pool(head, args.config, mesh, pool_dir, pool_settings, args.engine, args.workers)
        except (SpecError, OSError, ValueError) as exc:
            raise CliError(str(exc)) from exc
        except KeyboardInterrupt:
            print(f"\ninterrupted; rerun the same command to resume ({out})", file=sys.stderr)
            return 130
        if not summary["complete"]:
            raise CliError(f"the pool dataset {pool_dir} is incomplete ({summary['failed']} failed poses); rerun")
        log(f"pool: {summary['done']} poses ready ({summary['solved_now']} solved now, {summary['seconds']:.0f} s)")
    try:
        run_and_report(pool_dir, out, methods, bench, policy, cfg, args.policy, pool_settings,
                       config=args.config, log=log, policy_fraction=args.policy_fraction)
    except (SpecError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    except KeyboardInterrupt:
        print(f"\ninterrupted; rerun the same command to resume ({out})", file=sys.stderr)
        return 130
    log(f"done: {out / 'report.json'}, {out / 'al_benchmark.png'}")
    return 0


def _pool_pack(args: argparse.Namespace, settings) -> str | None:
    """The dataset pack to unpack as the pool: ``--pool-pack``, else the one shipped beside the config when it
    holds the default FEM pool; None to simulate (or for ``--pool``, ``--quick``, ``--synthetic``)."""
    from pathlib import Path

    from likeness.cli import CliError
    from models.errors import SpecError
    from offline.dataset.pack import read_header

    if args.pool is not None or args.simulate_pool or settings.synthetic or settings.nu is not None:
        if args.pool_pack and (args.pool is not None or args.simulate_pool or settings.nu is not None):
            raise CliError("--pool-pack cannot be combined with --pool, --simulate-pool or --skin-nu")
        return None
    shipped = Path(args.config).parent / PACK_NAME
    path = Path(args.pool_pack) if args.pool_pack else shipped
    if not path.is_file():
        if args.pool_pack:
            raise CliError(f"--pool-pack: {path} not found")
        return None
    try:
        manifest = read_header(path)["manifest"]
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    want = {"n_poses": settings.poses, "seed": settings.seed,
            "sampling": {"boundary_prob": settings.boundary_prob, "range_fraction": settings.range_fraction}}
    got = {k: manifest.get(k) for k in want}
    if got["sampling"] is not None:
        got["sampling"] = {k: got["sampling"].get(k) for k in want["sampling"]}
    if got != want:
        raise CliError(f"{path}: the pack holds a different pool ({got}) than this run asks for ({want}); "
                       "pass --simulate-pool to simulate it, or --pool DATASET")
    return str(path)


def _pack_made_by(path: str) -> str:
    from offline.dataset.pack import read_header

    return read_header(path)["header"].get("made_by") or "not recorded"
