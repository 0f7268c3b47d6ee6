"""``likeness offline al-benchmark``: GEN-LAL against the baselines on one pool, budget and set of seeds."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head, the output folder, the pool, the policy, the methods and the sizes."""
    p.description = ("Generate (or resume) a labelled pose dataset of the head, split it into a pool, a policy pool "
                     "and a test set, learn the GEN-LAL policy on the policy pool, then run GEN-LAL, random, greedy "
                     "fully informed, space-filling, committee variance and bmdal-reg's LCMD and MaxDist over several "
                     "seeds with the same budget, and write DIR/report.json and DIR/al_benchmark.png. Rerun the same "
                     "command to resume after an interruption.")
    p.add_argument("--config", required=True, help="head spec TOML (e.g. heads/sample/head.toml)")
    p.add_argument("--out", required=True, help="output folder (created, or resumed)")
    p.add_argument("--quick", action="store_true", help="analytic skin, small pool and budget (tests; seconds)")
    p.add_argument("--seeds", type=int, default=None, help="seeds per method (default 10; quick 2)")
    p.add_argument("--mesh", default=None, help="skin mesh folder (default: skin/ beside the config)")
    p.add_argument("--pool", default=None, help="use this consolidated pose dataset instead of DIR/pool")
    p.add_argument("--pool-pack", default=None,
                   help="unpack this dataset pack into DIR/pool instead of simulating the FEM pool, after checking "
                   "that it holds the pool the run asks for (poses, seed, sampling, clusters, element order; "
                   "default: the first al_pool*.npz beside the config that holds this pool)")
    p.add_argument("--simulate-pool", action="store_true",
                   help="simulate the FEM pool even when a pack of it (al_pool*.npz) is shipped beside the config")
    p.add_argument("--policy", default=None, help="use this learned policy file instead of learning one")
    p.add_argument("--methods", default=None, help="comma-separated subset of the methods (default: all)")
    p.add_argument("--init", type=int, default=None, help="random initial poses per seed (default 10; quick 6)")
    p.add_argument("--batch", type=int, default=None, help="poses per batch (default 10; quick 6)")
    p.add_argument("--budget", type=int, default=None, help="labelled poses at the end (default 100; quick 36)")
    p.add_argument("--policy-runs", type=int, default=None, help="simulated AL runs the policy learns from "
                   "(default 4; quick 2)")
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
    p.add_argument("--pool-poses", type=int, default=None,
                   help="poses in the pool dataset (default 480, the shipped FEM pack's; quick 150)")
    p.add_argument("--clusters", type=int, default=None,
                   help="candidate poses in this many clusters of heavy-tailed sizes (redundant candidates, as from "
                   "recorded performances); the test poses stay i.i.d. (default 0: i.i.d. candidates)")
    p.add_argument("--cluster-spread", type=float, default=None,
                   help="with --clusters: jitter of a pose around its centre, share of each range (default 0.05)")
    p.add_argument("--validation-seeds", type=int, default=None,
                   help="GEN-LAL: simulated AL runs per candidate setting on the policy pool's validation part when "
                   "the setting is chosen (default 1; more make a small difference less a matter of chance)")
    p.add_argument("--policy-model", default=None,
                   help="GEN-LAL regressor: features (ridge on uncertainty features, default) or cnn (the paper's)")
    p.add_argument("--element-order", type=int, choices=(1, 2), default=None,
                   help="FEM pool: 1 the skin mesh's linear tets (default, the shipped pack's), 2 the same tets "
                   "quadratic (the sample predictor's dataset; about 5x the time per pose)")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes for the pool's FEM poses and for the methods' runs (default: CPUs; the "
                   "curves are the same with any number)")
    p.add_argument("--engine", default="local", help="engine for the pool's FEM poses: local, dask-local, dask://")


def run(args: argparse.Namespace) -> int:
    """Run (or resume) the benchmark; 130 when interrupted."""
    import sys

    from offline.active.benchmark_job import BenchmarkJob, run_al_benchmark

    job = BenchmarkJob(
        config=args.config, out=args.out, quick=args.quick, seeds=args.seeds, mesh=args.mesh, pool=args.pool,
        pool_pack=args.pool_pack, simulate_pool=args.simulate_pool, policy=args.policy, methods=args.methods,
        init=args.init, batch=args.batch, budget=args.budget, policy_runs=args.policy_runs,
        policy_fraction=args.policy_fraction, synthetic=args.synthetic, sheet_grid=args.sheet_grid,
        sheet_stiffening=args.sheet_stiffening, skin_nu=args.skin_nu, workers=args.workers, engine=args.engine,
        pool_poses=args.pool_poses, clusters=args.clusters, cluster_spread=args.cluster_spread,
        policy_model=args.policy_model, element_order=args.element_order,
        validation_seeds=args.validation_seeds)
    try:
        run_al_benchmark(job)
    except KeyboardInterrupt:
        print(f"\ninterrupted; rerun the same command to resume ({args.out})", file=sys.stderr)
        return 130
    return 0
