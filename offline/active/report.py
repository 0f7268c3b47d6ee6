"""Assemble a benchmark run: load the data, learn (or load) the policy, run every method, write report and figure.

``report.json`` is written whole, atomically, by this module only. Units: µm for errors.
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from models.atomic import write_bytes
from offline.active.benchmark import (
    REPORT_FORMAT,
    REPORT_VERSION,
    BenchmarkSettings,
    paired_differences,
    paired_final_differences,
    run_benchmark,
)
from offline.active.learner import LearnerConfig
from offline.active.plot import plot_curves
from offline.active.policy import Policy, PolicySettings, learn_policy, pool_digest
from offline.active.pool import load_benchmark_data
from offline.active.selectors import BASELINES, genlal_selector

FIGURE = "al_benchmark.png"


def _file_hash(path: str | Path) -> str:
    return "sha256:" + hashlib.sha256(Path(path).read_bytes()).hexdigest()


def run_and_report(pool_dir: str | Path, out: str | Path, methods: Sequence[str], bench: BenchmarkSettings,
                   policy_settings: PolicySettings, cfg: LearnerConfig, policy_path: str | None, pool_settings: Any,
                   config: str, log: Callable[[str], None] = print, policy_fraction: float = 0.35,
                   workers: int = 1) -> dict[str, Any]:
    """The whole benchmark after the pool exists; returns the report (also written to ``out/report.json``). The
    methods' runs go to ``workers`` processes."""
    t0 = time.perf_counter()
    out = Path(out)
    data = load_benchmark_data(pool_dir, policy_fraction=policy_fraction)
    log(f"data: pool {len(data.pool)}, policy pool {len(data.policy)}, test {len(data.test)} poses, "
        f"{data.base.shape[0]} vertices, {data.pool.x.shape[1]} actuators")
    selectors = {}
    policy_info: dict[str, Any] | None = None
    if "genlal" in methods:
        if policy_path:
            policy = Policy.load(policy_path)
            if policy.n_actuators != data.pool.x.shape[1]:
                raise ValueError(f"{policy_path}: policy for {policy.n_actuators} actuators; this head has "
                                 f"{data.pool.x.shape[1]}")
            policy = policy.for_mesh(data.base, policy.scale)  # its own scale: the offsets it learned on
            policy_info = {"source": str(policy_path), "hash": _file_hash(policy_path), "learned": policy.info}
            log(f"policy: loaded {policy_path}")
        else:
            learned = out / "policy.npz"
            if learned.exists():
                policy = Policy.load(learned)
                if policy.info.get("policy_pool_hash") not in (None, pool_digest(data.policy.x, data.policy.y)):
                    raise ValueError(f"{learned} was learned on a different policy pool; use a new --out")
                if policy.info.get("settings") not in (None, json.loads(json.dumps(asdict(policy_settings)))):
                    raise ValueError(f"{learned} was learned with other policy settings; use a new --out")
                log(f"policy: loaded {learned} (learned by an earlier run)")
            else:
                log(f"policy: learning on the policy pool ({len(data.policy)} poses, {policy_settings.n_runs} "
                    "simulated runs)")
                policy = learn_policy(data.policy.x, data.policy.y, data.base, policy_settings, cfg,
                                      out / "policy_runs", log=log, clustered=data.policy_clustered,
                                      workers=workers)
                policy.save(learned)
            policy_info = {"source": "learned on the policy pool", "path": str(learned), "hash": _file_hash(learned),
                           "learned": policy.info}
    for name in methods:
        selectors[name] = genlal_selector(policy) if name == "genlal" else BASELINES[name]
    result = run_benchmark(data, selectors, bench, cfg, out, log=log, workers=workers)
    report = {
        "format": REPORT_FORMAT, "format_version": REPORT_VERSION,
        "units": "µm; n_labelled in poses",
        "inputs": {"config": str(config), "config_hash": _file_hash(config), **data.describe()},
        "pool_settings": asdict(pool_settings) if pool_settings is not None else None,
        "settings": result["settings"], "learner": result["learner"],
        "policy": policy_info, "policy_settings": asdict(policy_settings),
        "methods": list(methods),
        "summary": result["summary"],
        "oracle_fraction_to_random_final": result["summary"].get("greedy", {}).get("fraction_to_random_final"),
        "oracle_fraction_to_random_final_ci95": result["summary"].get("greedy", {}).get(
            "fraction_to_random_final_ci95"),
        "paired_fraction_difference": paired_differences(result["summary"]),
        "paired_final_error_difference_um": paired_final_differences(result["summary"]),
        "runs": {name: [{k: r[k] for k in ("seed", "n_labelled", "mean_euclidean_um", "l1_um", "select_seconds",
                                            "seconds")} | {"labelled_pool_rows": r["labelled"]} for r in rs]
                 for name, rs in result["runs"].items()},
        "figure": FIGURE,
        "honesty": "the test set is the dataset's test split: it is only evaluated, never selected from, and "
                   "plays no part in learning the policy or any setting; the policy is learned on a policy pool "
                   "disjoint from the benchmark pool and the test set; the greedy oracle reads every pool label "
                   "but not the test set",
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
        "seconds_this_invocation": round(time.perf_counter() - t0, 1),
    }
    write_bytes(out / "report.json", json.dumps(report, indent=1).encode())
    plot_curves(result["runs"], out / FIGURE,
                title=f"{data.dataset['id']}: {len(data.pool)}-pose pool, {len(data.test)} test poses, "
                      f"{bench.seeds} seeds")
    for name, s in result["summary"].items():
        f, ci = s["fraction_to_random_final"], s["fraction_to_random_final_ci95"]
        log(f"{name:14s} final {s['final_mean_euclidean_um']['mean']:8.1f} ± {s['final_mean_euclidean_um']['std']:6.1f}"
            f" µm   fraction to random's final: {'not reached' if f is None else f'{f:.2f}'}"
            f"{'' if ci is None else f' [{ci[0]:.2f}, {ci[1]:.2f}]'}"
            f" ({s['seeds_reaching_random_final']}/{len(result['runs'][name])} seeds)")
    return report
