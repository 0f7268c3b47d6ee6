"""The GEN-LAL benchmark as one resumable job (what ``likeness offline al-benchmark`` runs): a labelled pool of
the head's poses (unpacked from a shipped pack, or simulated), the policy learned on part of it, every method run
over several seeds with the same budget, and the report and figure."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from models.errors import ConfigError, SpecError, UsageError
from models.headspec import HeadSpec, load_head
from offline.active.benchmark import BenchmarkSettings
from offline.active.data import PoolSettings, ensure_pool
from offline.active.learner import LearnerConfig
from offline.active.policy import PolicySettings
from offline.active.report import run_and_report
from offline.active.selectors import METHODS

#: The quick sizes (analytic skin, small pool and budget: seconds; what tests run).
QUICK = {"pool": {"poses": 150, "seed": 11, "synthetic": True, "synthetic_grid": 12},
         "bench": {"init": 6, "batch": 6, "budget": 36, "seeds": 2},
         "policy": {"n_runs": 2, "init": 6, "batch": 8, "budget": 22, "candidates_per_step": 4, "pseudo_test": 12,
                    "epochs": 8, "committee": 2, "diversity": (0.0, 1.0), "validation_seeds": 1,
                    "family": 4, "family_sizes": (1, 4)},
         "learner": {"iterations": 25, "fine_tune_iterations": 4}}
#: The packs beside a head's config (``likeness offline dataset-pack`` of a pool's dataset) that a run takes as its
#: pool when one holds the pool it asks for: the default pool in ``al_pool.npz``, others under their own names.
PACK_GLOB = "al_pool*.npz"


@dataclass(frozen=True)
class BenchmarkJob:
    """One benchmark: the head, the output folder and what overrides the default (or ``quick``) sizes; ``pool`` a
    consolidated dataset to use as the pool, ``pool_pack`` a pack to unpack as it, ``policy`` a learned policy file;
    ``methods`` a comma-separated subset; the sheet and ``skin_nu`` options change the skin the pool is made on."""

    config: str
    out: str
    quick: bool = False
    seeds: int | None = None
    mesh: str | None = None
    pool: str | None = None
    pool_pack: str | None = None
    simulate_pool: bool = False
    policy: str | None = None
    methods: str | None = None
    init: int | None = None
    batch: int | None = None
    budget: int | None = None
    policy_runs: int | None = None
    policy_fraction: float = 0.35
    synthetic: bool = False
    sheet_grid: int | None = None
    sheet_stiffening: float | None = None
    skin_nu: float | None = None
    workers: int | None = None
    engine: str = "local"
    pool_poses: int | None = None
    clusters: int | None = None
    cluster_spread: float | None = None
    policy_model: str | None = None
    element_order: int | None = None
    validation_seeds: int | None = None


def settings_of(job: BenchmarkJob) -> tuple[PoolSettings, BenchmarkSettings, PolicySettings, LearnerConfig]:
    """The pool, benchmark, policy and learner settings of ``job`` (UsageError for values that cannot run)."""
    if job.seeds is not None and job.seeds < 1:
        raise UsageError(f"--seeds must be positive, got {job.seeds}")
    seeds = {"seeds": job.seeds} if job.seeds else {}
    if job.quick:
        pool = PoolSettings(**QUICK["pool"])
        bench = BenchmarkSettings(**{**QUICK["bench"], **seeds})
        policy = PolicySettings(**QUICK["policy"])
        cfg = LearnerConfig(**QUICK["learner"])
    else:
        pool, bench, policy, cfg = PoolSettings(), BenchmarkSettings(**seeds), PolicySettings(), LearnerConfig()
    overrides = {k: v for k, v in (("init", job.init), ("batch", job.batch), ("budget", job.budget)) if v is not None}
    if any(v < 1 for v in overrides.values()):
        raise UsageError(f"--init, --batch and --budget must be positive, got {overrides}")
    if overrides:
        bench = replace(bench, **overrides)
        policy = replace(policy, init=bench.init, batch=bench.batch, budget=bench.budget)
    if job.policy_runs is not None:
        if job.policy_runs < 1:
            raise UsageError(f"--policy-runs must be positive, got {job.policy_runs}")
        policy = replace(policy, n_runs=job.policy_runs)
    sheet = {k: v for k, v in (("synthetic_grid", job.sheet_grid), ("synthetic_stiffening", job.sheet_stiffening))
             if v is not None}
    if job.synthetic or sheet:
        pool = replace(pool, synthetic=True, **sheet)
    pool_over = {k: v for k, v in (("poses", job.pool_poses), ("clusters", job.clusters),
                                   ("cluster_spread", job.cluster_spread)) if v is not None}
    if job.pool_poses is not None and job.pool_poses < 10:
        raise UsageError(f"--pool-poses must be at least 10, got {job.pool_poses}")
    if (job.clusters is not None and job.clusters < 0) or (job.cluster_spread is not None and job.cluster_spread <= 0):
        raise UsageError("--clusters must be >= 0 and --cluster-spread positive")
    pool = replace(pool, **pool_over, policy_fraction=job.policy_fraction)
    if job.element_order is not None:
        if job.element_order not in (1, 2):
            raise UsageError(f"--element-order must be 1 or 2, got {job.element_order}")
        if pool.synthetic and job.element_order != 1:
            raise UsageError("--element-order 2 makes the FEM pool quadratic; the analytic sheet (--quick, "
                             "--synthetic) has no elements")
        pool = replace(pool, element_order=job.element_order)
    if job.validation_seeds is not None:
        if job.validation_seeds < 1:
            raise UsageError(f"--validation-seeds must be positive, got {job.validation_seeds}")
        policy = replace(policy, validation_seeds=job.validation_seeds)
    if job.policy_model is not None:
        from offline.active.policy import MODELS

        if job.policy_model not in MODELS:
            raise UsageError(f"--policy-model must be one of {', '.join(MODELS)}, got {job.policy_model}")
        policy = replace(policy, model=job.policy_model)
    if job.skin_nu is not None:
        if not 0.0 < job.skin_nu < 0.5:
            raise UsageError(f"--skin-nu must lie in (0, 0.5), got {job.skin_nu}")
        if pool.synthetic:
            raise UsageError("--skin-nu changes the FEM skin; the analytic sheet (--quick, --synthetic) has none")
        pool = replace(pool, nu=job.skin_nu)
    return pool, bench, policy, cfg


def run_workers(workers: int | None) -> int:
    """Processes for the methods' runs: ``workers``, else one per CPU this process may use."""
    import os

    if workers is not None:
        if workers < 1:
            raise UsageError(f"--workers must be positive, got {workers}")
        return workers
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def _wanted_pool(settings: PoolSettings) -> dict:
    """What a pack's manifest must record to stand in for the pool of ``settings``."""
    sampling = {"boundary_prob": settings.boundary_prob, "range_fraction": settings.range_fraction,
                "clusters": settings.clusters or None,
                "cluster_spread": settings.cluster_spread if settings.clusters else None}
    return {"n_poses": settings.poses, "seed": settings.seed, "sampling": sampling,
            "element_order": settings.element_order}


def _held_pool(path: Path) -> dict:
    """The pool a pack holds, in the terms of :func:`_wanted_pool` (read from its header only)."""
    from offline.dataset.pack import read_header

    manifest = read_header(path)["manifest"]
    held = manifest.get("sampling") or {}
    return {"n_poses": manifest.get("n_poses"), "seed": manifest.get("seed"),
            "sampling": {k: held.get(k) for k in ("boundary_prob", "range_fraction", "clusters", "cluster_spread")},
            "element_order": (manifest.get("problem") or {}).get("element_order", 1)}


def pool_pack(job: BenchmarkJob, settings: PoolSettings) -> str | None:
    """The dataset pack to unpack as the pool: ``pool_pack`` (any pool, checked against the run's settings), else
    the first pack shipped beside the config (``al_pool*.npz``) that holds the pool the run asks for; None to
    simulate (and for ``pool``, ``simulate_pool``, the analytic sheet and ``skin_nu``)."""
    if job.pool is not None or job.simulate_pool or settings.synthetic or settings.nu is not None:
        if job.pool_pack and (job.pool is not None or job.simulate_pool or settings.nu is not None):
            raise UsageError("--pool-pack cannot be combined with --pool, --simulate-pool or --skin-nu")
        return None
    want = _wanted_pool(settings)
    if job.pool_pack:
        path = Path(job.pool_pack)
        if not path.is_file():
            raise UsageError(f"--pool-pack: {path} not found")
        got = _held_pool(path)
        if got != want:
            raise UsageError(f"{path}: the pack holds a different pool ({got}) than this run asks for ({want}); "
                             "pass --simulate-pool to simulate it, or --pool DATASET")
        return str(path)
    for path in sorted(Path(job.config).parent.glob(PACK_GLOB)):
        if _held_pool(path) == want:
            return str(path)
    return None


def _prepare_pool(job: BenchmarkJob, head: HeadSpec, settings: PoolSettings, pool_dir: Path,
                  log: Callable[[str], None]) -> None:
    """Unpack the shipped or given pack into ``pool_dir``, or simulate the pool there (resuming)."""
    pack = pool_pack(job, settings)
    if pack is not None:
        from offline.dataset.pack import read_header, unpack_dataset

        made_by = read_header(pack)["header"].get("made_by") or "not recorded"
        log(f"pool: unpacking {pack} into {pool_dir} (made by: {made_by})")
        try:
            unpack_dataset(pack, pool_dir)
        except SpecError:
            raise
        except (OSError, ValueError) as exc:
            raise ConfigError(str(exc)) from exc
        return
    mesh = job.mesh or str(Path(job.config).parent / "skin")
    log(f"pool: {settings.poses} {'analytic' if settings.synthetic else 'FEM'} poses into {pool_dir} "
        "(resumes if present)")
    try:
        summary = ensure_pool(head, job.config, mesh, pool_dir, settings, job.engine, job.workers)
    except SpecError:
        raise
    except (OSError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    if not summary["complete"]:
        raise ConfigError(f"the pool dataset {pool_dir} is incomplete ({summary['failed']} failed poses); rerun")
    log(f"pool: {summary['done']} poses ready ({summary['solved_now']} solved now, {summary['seconds']:.0f} s)")


def run_al_benchmark(job: BenchmarkJob, log: Callable[[str], None] | None = None) -> Path:
    """Pool, policy, every method over the seeds, report and figure; returns the report's path. Resumable: the
    same job after an interruption (KeyboardInterrupt passes through) goes on where it stopped."""
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    if log is None:
        import sys

        def log(msg: str) -> None:
            print(f"[{time.perf_counter() - t0:7.0f} s] {msg}", file=sys.stderr, flush=True)

    head = load_head(job.config)
    methods = tuple(m.strip() for m in job.methods.split(",")) if job.methods else METHODS
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise UsageError(f"--methods: unknown {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    pool_settings, bench, policy, cfg = settings_of(job)
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    pool_dir = Path(job.pool) if job.pool else out / "pool"
    if job.pool is None:
        _prepare_pool(job, head, pool_settings, pool_dir, log)
    try:
        run_and_report(pool_dir, out, methods, bench, policy, cfg, job.policy, pool_settings,
                       config=job.config, log=log, policy_fraction=job.policy_fraction,
                       workers=run_workers(job.workers))
    except SpecError:
        raise
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    log(f"done: {out / 'report.json'}, {out / 'al_benchmark.png'}")
    return out / "report.json"

