"""The active-learning benchmark: every method over several seeds on one pool, budget and test set.

For each seed, all methods start from the same random initial labelled set drawn from the pool and add ``batch``
poses per step until ``budget``; after each step the predictor is retrained from scratch (same schedule and seed
for every method) and its test mean Euclidean error and L1 are recorded. Each (method, seed) run is checkpointed
after every batch (``runs/METHOD_sSEED.json``), so a killed benchmark resumes where it stopped. With ``workers`` > 1
the runs go to that many worker processes (one interpreter and one thread each; a run is deterministic given its
seed, so the curves are the same as one process computes them).

``fraction_to_random_final``: per seed, the sample count at which a method's error curve first reaches random's
final error (linear interpolation between batches), divided by random's final sample count; the report gives the
mean over the seeds where it is reached and the number of such seeds (a method that never reaches it within the
budget has no fraction for that seed, and its mean is null if no seed reaches it).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from offline.active import learner
from offline.active.learner import LearnerConfig
from offline.active.pool import BenchmarkData
from offline.active.selectors import SelectionContext, Selector

REPORT_FORMAT = "likeness-al-benchmark"
REPORT_VERSION = 1


@dataclass(frozen=True)
class BenchmarkSettings:
    """Budget and schedule shared by every method."""

    init: int = 10
    batch: int = 10
    budget: int = 100
    seeds: int = 10


def run_method(name: str, selector: Selector, data: BenchmarkData, seed: int, settings: BenchmarkSettings,
               cfg: LearnerConfig, checkpoint: Path, log: Callable[[str], None] = print) -> dict[str, Any]:
    """One AL run of ``selector`` (resumed from ``checkpoint`` when it holds a partial run); returns its curve."""
    pool = data.pool
    pool_hash = pool.digest()
    if checkpoint.exists():
        run = json.loads(checkpoint.read_text())
        if run.get("pool_hash") != pool_hash:
            raise ValueError(f"{checkpoint}: made on a different pool (the dataset changed since); use a new --out")
        if run.get("complete"):
            return run
    else:
        init = np.random.default_rng([seed, 0x1417]).choice(len(pool), size=settings.init, replace=False)
        run = {"method": name, "seed": seed, "pool_hash": pool_hash, "labelled": [int(i) for i in init],
               "n_labelled": [],
               "mean_euclidean_um": [], "l1_um": [], "select_seconds": [], "complete": False}
    labelled = np.asarray(run["labelled"], dtype=np.int64)
    rng = np.random.default_rng([seed, 0x5E1, settings.init])
    if "rng_state" in run:  # a resumed run continues the stream where the checkpoint left it
        rng.bit_generator.state = run["rng_state"]
    t0 = time.perf_counter()
    while True:
        state = learner.fit(pool.x[labelled], pool.y[labelled], cfg)
        if len(run["n_labelled"]) == 0 or run["n_labelled"][-1] != len(labelled):
            err = learner.errors(state, data.test.x, data.test.y)
            run["n_labelled"].append(len(labelled))
            run["mean_euclidean_um"].append(err["mean_euclidean_um"])
            run["l1_um"].append(err["l1_um"])
        if len(labelled) >= settings.budget:
            break
        cand = np.setdiff1d(np.arange(len(pool)), labelled)
        b = min(settings.batch, settings.budget - len(labelled), len(cand))
        ctx = SelectionContext(x=pool.x, labelled=labelled, candidates=cand, y_labelled=pool.y[labelled],
                               state=state, batch=b, rng=rng, config=cfg,
                               oracle_y=pool.y if name.startswith("greedy") else None)
        t1 = time.perf_counter()
        chosen = np.asarray(selector(ctx), dtype=np.int64)
        if len(np.unique(chosen)) != b or np.isin(chosen, labelled).any():
            raise RuntimeError(f"{name} selected an invalid batch {chosen.tolist()}")
        run["select_seconds"].append(round(time.perf_counter() - t1, 3))
        labelled = np.concatenate([labelled, chosen])
        run["labelled"] = [int(i) for i in labelled]
        run["rng_state"] = rng.bit_generator.state
        write_bytes(checkpoint, json.dumps(run).encode())
        log(f"{name} seed {seed}: {len(labelled)}/{settings.budget} labelled, test error "
            f"{run['mean_euclidean_um'][-1]:.1f} µm before this batch")
    run["complete"] = True
    run["seconds"] = round(run.get("seconds", 0.0) + time.perf_counter() - t0, 2)
    write_bytes(checkpoint, json.dumps(run).encode())
    return run


def first_reach(n: Sequence[float], err: Sequence[float], target: float) -> float | None:
    """Smallest sample count at which the piecewise-linear curve (n, err) reaches ``target`` (None: never)."""
    for i, e in enumerate(err):
        if e <= target:
            if i == 0:
                return float(n[0])
            e0, n0, n1 = err[i - 1], n[i - 1], n[i]
            return float(n0 + (n1 - n0) * (e0 - target) / (e0 - e))
    return None


def ci95(values: Sequence[float]) -> list[float] | None:
    """Student-t 95 % interval of the mean of ``values`` (None for fewer than two)."""
    from scipy import stats

    v = np.asarray([x for x in values if x is not None], dtype=float)
    if len(v) < 2:
        return None
    h = float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v)))
    return [float(v.mean() - h), float(v.mean() + h)]


def mean_curve(rs: list[dict[str, Any]], key: str = "mean_euclidean_um") -> dict[str, list]:
    """The mean curve over seeds with its pointwise 95 % interval (runs of the full length only)."""
    n = max((r["n_labelled"] for r in rs), key=len)
    curves = np.array([r[key] for r in rs if len(r[key]) == len(n)])
    cis = [ci95(curves[:, i]) for i in range(len(n))]
    return {"n_labelled": list(n), "mean": curves.mean(axis=0).tolist(),
            "ci95_lo": [c[0] if c else None for c in cis], "ci95_hi": [c[1] if c else None for c in cis]}


def paired_differences(summary: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per pair of methods (A vs B): mean per-seed fraction of A minus B, its 95 % interval, seeds counted."""
    out: dict[str, dict[str, Any]] = {}
    for a, sa in summary.items():
        for b, sb in summary.items():
            if a == b:
                continue
            pa, pb = sa["fraction_to_random_final_per_seed"], sb["fraction_to_random_final_per_seed"]
            d = [pa[k] - pb[k] for k in pa if pa.get(k) is not None and pb.get(k) is not None]
            out[f"{a} - {b}"] = {"mean": float(np.mean(d)) if d else None, "ci95": ci95(d), "seeds": len(d)}
    return out


def paired_final_differences(summary: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per pair of methods (A vs B): mean per-seed difference of their final test errors (µm, A minus B, the same
    seeds in order), its 95 % interval and the seed count: which method ends lower at the full budget."""
    out: dict[str, dict[str, Any]] = {}
    for a, sa in summary.items():
        for b, sb in summary.items():
            if a == b:
                continue
            fa, fb = sa["final_mean_euclidean_um"]["per_seed"], sb["final_mean_euclidean_um"]["per_seed"]
            d = [x - y for x, y in zip(fa, fb, strict=False)]
            out[f"{a} - {b}"] = {"mean": float(np.mean(d)) if d else None, "ci95": ci95(d), "seeds": len(d)}
    return out


def summarize(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Per-method summary: final errors over seeds, ``fraction_to_random_final``, intervals and mean curves."""
    random_by_seed = {r["seed"]: r for r in runs.get("random", [])}
    out: dict[str, Any] = {}
    for name, rs in runs.items():
        finals = np.array([r["mean_euclidean_um"][-1] for r in rs])
        per_seed: dict[str, float | None] = {}
        for r in rs:
            ref = random_by_seed.get(r["seed"])
            if ref is None:
                continue
            n_final = ref["n_labelled"][-1]
            reach = first_reach(r["n_labelled"], r["mean_euclidean_um"], ref["mean_euclidean_um"][-1])
            per_seed[str(r["seed"])] = None if reach is None else reach / n_final
        reached = [v for v in per_seed.values() if v is not None]
        out[name] = {
            "final_mean_euclidean_um": {"mean": float(finals.mean()), "std": float(finals.std()),
                                        "ci95": ci95(finals.tolist()), "per_seed": finals.tolist()},
            "final_l1_um_mean": float(np.mean([r["l1_um"][-1] for r in rs])),
            "fraction_to_random_final": float(np.mean(reached)) if reached else None,
            "fraction_to_random_final_ci95": ci95(reached),
            "fraction_to_random_final_per_seed": per_seed,
            "seeds_reaching_random_final": len(reached),
            "select_seconds_total_mean": float(np.mean([sum(r["select_seconds"]) for r in rs])),
            "curve_mean_euclidean_um": mean_curve(rs),
        }
    return out


def run_benchmark(data: BenchmarkData, selectors: dict[str, Selector], settings: BenchmarkSettings,
                  cfg: LearnerConfig, out_dir: str | Path, log: Callable[[str], None] = print,
                  workers: int = 1) -> dict[str, Any]:
    """Run every method for every seed (resumable; in ``workers`` processes); returns the per-method runs and their
    summary."""
    if settings.budget > len(data.pool) or settings.init >= settings.budget:
        raise ValueError(f"budget {settings.budget} must exceed init {settings.init} and fit in the pool "
                         f"({len(data.pool)} poses)")
    runs_dir = Path(out_dir) / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(name, seed) for seed in range(settings.seeds) for name in selectors]
    total = len(jobs)
    done: dict[tuple[str, int], dict[str, Any]] = {}

    def finished(name: str, seed: int, run: dict[str, Any], seconds: float) -> None:
        done[name, seed] = run
        log(f"[{len(done)}/{total}] {name} seed {seed}: final test error {run['mean_euclidean_um'][-1]:.1f} µm "
            f"with {run['n_labelled'][-1]} poses ({seconds:.0f} s)")

    if workers <= 1 or total <= 1:
        for name, seed in jobs:
            t0 = time.perf_counter()
            run = run_method(name, selectors[name], data, seed, settings, cfg, runs_dir / f"{name}_s{seed}.json",
                             log=log)
            finished(name, seed, run, time.perf_counter() - t0)
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # the slowest rules first, so that no long run is left alone at the end
        slow_first = sorted(jobs, key=lambda j: (j[0] not in _SLOW, j[1]))
        with ProcessPoolExecutor(min(workers, total), mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                 initargs=(data, selectors, settings, cfg, runs_dir)) as ex:
            futures = {ex.submit(_worker_run, name, seed): (name, seed) for name, seed in slow_first}
            for fut in as_completed(futures):
                run, seconds = fut.result()
                finished(*futures[fut], run, seconds)
    runs = {name: [done[name, seed] for seed in range(settings.seeds)] for name in selectors}
    return {"runs": runs, "summary": summarize(runs), "settings": asdict(settings), "learner": asdict(cfg)}


#: Rules that retrain many predictors per batch (the oracle's family, the committee): started first in parallel.
_SLOW = ("greedy", "committee", "genlal")
_WORKER: dict[str, Any] = {}


def _worker_init(data: BenchmarkData, selectors: dict[str, Selector], settings: BenchmarkSettings,
                 cfg: LearnerConfig, runs_dir: Path) -> None:
    """A benchmark worker process: one thread for torch and BLAS (the runs are the parallelism), the shared
    inputs kept for its runs."""
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    _WORKER["limits"] = threadpool_limits(1)
    _WORKER.update(data=data, selectors=selectors, settings=settings, cfg=cfg, runs_dir=runs_dir)


def _worker_run(name: str, seed: int) -> tuple[dict[str, Any], float]:
    """One (method, seed) run in a worker; its curve and its seconds."""
    w = _WORKER
    t0 = time.perf_counter()
    run = run_method(name, w["selectors"][name], w["data"], seed, w["settings"], w["cfg"],
                     w["runs_dir"] / f"{name}_s{seed}.json", log=lambda msg: None)
    return run, time.perf_counter() - t0
