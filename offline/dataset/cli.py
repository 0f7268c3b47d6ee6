"""``likeness offline dataset``: simulate sampled poses of a head on an engine into a resumable dataset folder."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``dataset`` tool."""
    p = sub.add_parser("dataset", help="simulate sampled actuator poses into a pose dataset (resumable)",
                       description="Sample actuator poses of a head (uniform or boundary values, group constraints "
                       "honoured, duplicates removed, seeded), solve each with the skin FEM through the link map "
                       "m(p), warm-started from the nearest solved pose, and store one file per pose plus a "
                       "manifest. Rerun the same command to resume after an interruption.")
    p.add_argument("--config", required=True, help="head spec TOML (e.g. heads/sample/head.toml)")
    p.add_argument("--mesh", help="skin mesh folder (e.g. heads/sample/skin)")
    p.add_argument("--linkmap", help="link map file m(p) (default: the head's paths.linkmap)")
    p.add_argument("--synthetic", action="store_true",
                   help="use the analytic test sheet instead of the FEM (pipeline smoke tests and benchmarks)")
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
    p.add_argument("--element-order", type=int, choices=(1, 2), default=1,
                   help="1: the mesh's linear tets; 2: the same tets quadratic (mid-edge nodes; about 5x the time "
                   "per Newton iteration, far less discretization error in a thin skin)")
    p.add_argument("--backend", default="auto", help="sparse solver backend for the FEM (auto|cholmod|pardiso|superlu)")
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
    p.set_defaults(func=run)
    k = sub.add_parser("dataset-pack", help="pack a pose dataset into one compressed file (lossless, hash-checked)",
                       description="Write what training and evaluation read of a dataset folder (manifest, samples, "
                       "base surface, splits, actuators, offsets, status) into one compressed .npz, to ship with a "
                       "head or move between machines; the pack records the dataset's content hash and the command "
                       "that made it. `likeness offline al-benchmark` unpacks the pool it finds beside the config.")
    k.add_argument("--dataset", required=True, help="dataset folder")
    k.add_argument("--out", required=True, help="pack file to write (.npz)")
    k.add_argument("--made-by", default="", help="the command that simulated the dataset (recorded in the pack)")
    k.set_defaults(func=run_pack)
    u = sub.add_parser("dataset-unpack", help="unpack a dataset pack into a dataset folder (hash-checked)",
                       description="Write a pack from `likeness offline dataset-pack` back as a consolidated dataset "
                       "folder (no per-pose files) and check its content hash, so training and evaluation read "
                       "exactly the packed dataset. Refuses a folder that holds another dataset.")
    u.add_argument("pack", help="pack file (.npz)")
    u.add_argument("--out", required=True, help="dataset folder to write")
    u.set_defaults(func=run_unpack)


def run(args: argparse.Namespace) -> int:
    """Build the problem and engine, then generate (or resume) the dataset."""
    import json
    import sys

    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head
    from offline.dataset.generate import generate_dataset
    from offline.dataset.sampling import sample_poses
    from offline.engine import make_engine

    try:
        head = load_head(args.config)
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    if args.poses < 1:
        raise CliError(f"--poses must be positive, got {args.poses}")
    from offline.dataset.sampling import sample_ranges

    try:
        lo, hi = sample_ranges(head, args.range_fraction)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    if args.synthetic and args.element_order != 1:
        raise CliError("--element-order applies to the FEM skin, not to --synthetic")
    if args.synthetic:
        from offline.dataset.synthetic import SyntheticSpec

        spec = SyntheticSpec(tuple(float(x) for x in lo), tuple(float(x) for x in hi))
    else:
        if not args.mesh:
            raise CliError("--mesh is required (or --synthetic for the analytic test sheet)")
        linkmap = args.linkmap or head.path("linkmap")
        if linkmap is None:
            raise CliError("--linkmap is required: the head config has no paths.linkmap")
        try:
            from offline.dataset.fem_problem import FemSpec, material_fields
        except ImportError as exc:
            raise CliError(f"the skin FEM is not available in this installation: {exc}") from exc
        try:
            material = head.skin_material()
        except SpecError as exc:
            raise CliError(str(exc)) from exc
        spec = FemSpec(config=str(args.config), mesh=str(args.mesh), linkmap=str(linkmap),
                       backend=args.backend, threads=args.threads_per_worker, element_order=args.element_order,
                       **material_fields(material))
        if material is None:
            print(f"note: {args.config} has no [skin_material]; simulating with {spec.material_source}",
                  file=sys.stderr)
        try:
            spec.check()
        except (SpecError, OSError, ValueError) as exc:
            raise CliError(str(exc)) from exc
    try:
        samples = sample_poses(head, args.poses, seed=args.seed, boundary_prob=args.boundary_prob,
                               range_fraction=args.range_fraction)
        engine = make_engine(args.engine, args.workers, args.threads_per_worker)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    import signal

    def _terminate(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)  # finish cleanly: in-flight poses are written, workers stop
    if args.select is None and (args.budget is not None or args.policy is not None):
        raise CliError("--budget and --policy need --select genlal|random")
    if args.select is not None:
        if args.budget is None:
            raise CliError("--select needs --budget (poses to simulate)")
        policy = None
        if args.select == "genlal":
            if not args.policy:
                raise CliError("--select genlal needs --policy FILE (likeness offline al-benchmark writes "
                               "DIR/policy.npz)")
            from offline.active.policy import Policy

            try:
                policy = Policy.load(args.policy)
            except ValueError as exc:
                raise CliError(str(exc)) from exc
    rest_pose = None if args.synthetic else head.neutral_pose  # the FEM skin is at rest at the head's neutral
    try:
        with engine:
            if args.select is not None:
                import torch

                from offline.active.loop import grow_dataset

                torch.set_num_threads(1)
                try:
                    summary = grow_dataset(
                        args.out, spec, samples, select=args.select, budget=args.budget, batch=args.batch,
                        init=args.init or args.batch, policy=policy, head=head.name, names=head.actuator_names,
                        units=units, lo=lo, hi=hi, engine=engine, seed=args.seed,
                        sampling={"boundary_prob": args.boundary_prob, "range_fraction": args.range_fraction},
                        progress_stream=None if args.quiet else sys.stderr, rest_pose=rest_pose)
                except ValueError as exc:
                    raise CliError(str(exc)) from exc
                print(json.dumps(summary, indent=1))
                return 0
            summary = generate_dataset(
                args.out, spec, samples, head=head.name, names=head.actuator_names, units=units, lo=lo, hi=hi,
                engine=engine, seed=args.seed,
                sampling={"boundary_prob": args.boundary_prob, "range_fraction": args.range_fraction},
                progress_stream=None if args.quiet else sys.stderr, max_poses=args.max_poses,
                rest_pose=rest_pose,
            )
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    except KeyboardInterrupt:
        print(f"\ninterrupted; rerun the same command to resume ({args.out})", file=sys.stderr)
        return 130
    print(json.dumps(summary, indent=1))
    return 0 if summary["failed"] == 0 else 1


def run_pack(args: argparse.Namespace) -> int:
    """Pack a dataset folder and print what the pack holds."""
    from pathlib import Path

    from likeness.cli import CliError
    from models.errors import SpecError
    from offline.dataset.pack import pack_dataset

    try:
        header = pack_dataset(args.dataset, args.out, made_by=args.made_by)
    except (SpecError, OSError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    size = Path(args.out).stat().st_size
    print(f"packed {header['n_poses']} poses ({header['converged']} converged, {header['n_vertices']} vertices) "
          f"into {args.out} ({size / 1e6:.1f} MB); content {header['content_hash']}")
    return 0


def run_unpack(args: argparse.Namespace) -> int:
    """Unpack a pack into a dataset folder and say what it holds and who made it."""
    from likeness.cli import CliError
    from models.errors import SpecError
    from offline.dataset.pack import read_header, unpack_dataset

    try:
        header = read_header(args.pack)["header"]
        ds = unpack_dataset(args.pack, args.out)
    except (SpecError, OSError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    print(f"unpacked {header['n_poses']} poses ({len(ds.usable)} converged, {header['n_vertices']} vertices) into "
          f"{args.out}; content {ds.content_hash()}; made by: {header['made_by'] or 'not recorded'}")
    return 0
