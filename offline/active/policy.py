"""GEN-LAL: learn a selection policy from simulated AL runs (Algorithm 1) and select batches with it (Algorithm 2).

Learning (``learn_policy``): the policy pool is split once into a simulation part and a validation part. On the
simulation part, simulated random AL runs (``offline.active.labels``) record, for candidates at each step, their
features and the pseudo-test error reduction that adding each one brings under the benchmark's own from-scratch
training, averaged over training seeds and ranked within the step. A regressor learns features → ranked reduction:

- ``features`` (default): ridge regression on the ranked uncertainty features (``offline.active.uncertainty``:
  committee disagreement, distance to labelled poses, predicted strain, ...), their squares and pairwise products;
- ``cnn``: the paper's 1-D CNN over the predicted mesh (``offline.active.regressor``), kept as an option.

Its held-out fit (leave one simulated run out; one step, with a single run) is measured per labelled-set size:
R² and rank correlation.

Selection (``Policy.select``): score every candidate, then build the batch greedily with a diversity term: each pick
maximizes the score's rank plus ``diversity`` × the candidate's distance to the labelled and already chosen poses
(over its median), so a batch does not pile up on similar poses. ``diversity`` is chosen among the settings'
values by short simulated AL runs on the validation part of the policy pool (never on the benchmark's pool or
test set); 0 is plain top-k.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from offline.active import learner
from offline.active.batches import batch_family, batch_features, diverse_batch, family_seed
from offline.active.features import candidate_features, morton_order
from offline.active.labels import (
    LabelSettings,
    RunLabels,
    concat_runs,
    simulate_batch_run,
    simulate_run,
    split_simulation,
)
from offline.active.learner import KsnnState, LearnerConfig
from offline.active.regressor import predict_reduction, train_regressor
from offline.active.uncertainty import committee, rank01, state_features

POLICY_FORMAT = "likeness-genlal-policy"
MODELS = ("features", "cnn")


@dataclass(frozen=True)
class PolicySettings:
    """How the policy is learned: simulated runs and their labels, the regressor, the validated diversity."""

    n_runs: int = 4
    init: int = 10
    batch: int = 10
    budget: int = 100
    candidates_per_step: int = 12
    pseudo_test: int = 150
    label_seeds: int = 2
    committee: int = 3
    model: str = "features"
    epochs: int = 60  # cnn only
    ridge: float = 1e-2
    diversity: tuple[float, ...] = (0.0, 0.5, 2.0)
    validation_fraction: float = 0.4
    validation_seeds: int = 1
    seed: int = 0
    labels: str = "batch"  # "batch": whole candidate batches labelled; "candidate": single poses (cnn: always)
    family: int = 12  # batch labels: candidate batches per step
    family_sizes: tuple[int, ...] = (1, 4, 12)  # batch labels: family sizes at selection, chosen on validation

    @property
    def label_mode(self) -> str:
        return "candidate" if self.model == "cnn" else self.labels

    def label_settings(self) -> LabelSettings:
        return LabelSettings(init=self.init, batch=self.batch, budget=self.budget,
                             candidates_per_step=self.candidates_per_step, pseudo_test=self.pseudo_test,
                             label_seeds=self.label_seeds, committee=self.committee, seed=self.seed,
                             family=self.family)


def _quad(f: np.ndarray) -> np.ndarray:
    """[1, f, f_i f_j (i <= j)]: the ridge model's terms."""
    i, j = np.triu_indices(f.shape[1])
    return np.concatenate([np.ones((len(f), 1)), f, f[:, i] * f[:, j]], axis=1)


def fit_ridge(f: np.ndarray, t: np.ndarray, ridge: float) -> np.ndarray:
    """Coefficients of the quadratic ridge model (no penalty on the constant)."""
    q = _quad(np.asarray(f, np.float64))
    pen = ridge * len(q) * np.eye(q.shape[1])
    pen[0, 0] = 0.0
    return np.linalg.solve(q.T @ q + pen, q.T @ np.asarray(t, np.float64))


def _fit(rows: RunLabels, settings: PolicySettings, log: Callable[[str], None] | None = None) -> bytes:
    if settings.model == "features":
        return fit_ridge(rows.feats, rows.target, settings.ridge).tobytes()
    return train_regressor(rows.cnn, rows.target * 2.0, epochs=settings.epochs, seed=settings.seed, log=log)


def _predict(model: str, regressor: bytes, feats: np.ndarray | None, cnn) -> np.ndarray:
    if model == "features":
        return _quad(np.asarray(feats, np.float64)) @ np.frombuffer(regressor, dtype=np.float64)
    return predict_reduction(regressor, cnn)


@dataclass
class Policy:
    """A learned GEN-LAL policy: the regressor, its kind and diversity, and the CNN's vertex order and scale."""

    regressor: bytes
    order: np.ndarray
    scale: np.ndarray
    n_actuators: int
    info: dict

    @property
    def model(self) -> str:
        return self.info.get("model", "cnn")

    @property
    def diversity(self) -> float:
        return float(self.info.get("diversity", 0.0))

    @property
    def label_mode(self) -> str:
        return str(self.info.get("labels", "candidate"))

    @property
    def family(self) -> int:
        return int(self.info.get("family", 1))

    def scores(self, state: KsnnState, x_labelled: np.ndarray, y_labelled: np.ndarray, x_cand: np.ndarray,
               cfg: LearnerConfig) -> np.ndarray:
        """Predicted (ranked) error reduction of each candidate under ``state`` (higher is better)."""
        if self.model == "cnn":
            if len(self.order) != state.W2.shape[2]:
                raise ValueError(f"policy learned on {len(self.order)} vertices; the predictor has "
                                 f"{state.W2.shape[2]} (give the policy this mesh's base surface with for_mesh)")
            return predict_reduction(self.regressor, candidate_features(state, x_labelled, x_cand, self.order,
                                                                        self.scale))
        members = committee(state, x_labelled, y_labelled, cfg, int(self.info.get("committee", 3)))
        return _predict("features", self.regressor, state_features(members, x_labelled, x_cand), None)

    def select(self, state: KsnnState, x_labelled: np.ndarray, y_labelled: np.ndarray, x_cand: np.ndarray,
               batch: int, cfg: LearnerConfig) -> np.ndarray:
        """Algorithm 2: positions in ``x_cand`` of the chosen batch. Batch labels: the family member with the largest
        predicted reduction; candidate labels: a diverse batch over the candidates' scores."""
        if self.label_mode == "batch":
            return self.select_batch(state, x_labelled, y_labelled, x_cand, batch, cfg)
        s = self.scores(state, x_labelled, y_labelled, x_cand, cfg)
        return diverse_batch(s, x_labelled, x_cand, batch, self.diversity)

    def select_batch(self, state: KsnnState, x_labelled: np.ndarray, y_labelled: np.ndarray, x_cand: np.ndarray,
                     batch: int, cfg: LearnerConfig) -> np.ndarray:
        """The batch-label policy: the committee's ranked features, the family of ``self.family`` candidate
        batches, the regressor's predicted reduction of each; the best one."""
        rng = family_seed(len(x_labelled), 0x5E1)
        if self.family <= 1:
            return batch_family(np.zeros((len(x_cand), 1)), x_labelled, x_cand, batch, 1, rng)[0]
        members = committee(state, x_labelled, y_labelled, cfg, int(self.info.get("committee", 3)))
        ranked = state_features(members, x_labelled, x_cand)
        fam = batch_family(ranked[:, :-1], x_labelled, x_cand, batch, self.family, rng)
        pred = _predict("features", self.regressor, batch_features(ranked, x_labelled, x_cand, fam), None)
        return fam[int(np.argmax(pred))]

    def with_diversity(self, diversity: float) -> Policy:
        return Policy(self.regressor, self.order, self.scale, self.n_actuators, {**self.info, "diversity": diversity})

    def with_setting(self, key: str, value: float) -> Policy:
        """The same regressor with the validated selection setting ``key`` (``diversity`` or ``family``)."""
        return Policy(self.regressor, self.order, self.scale, self.n_actuators, {**self.info, key: value})

    def for_mesh(self, base: np.ndarray, scale: np.ndarray) -> Policy:
        """The same regressor applied to another mesh (vertex order and offset scale of that mesh)."""
        return Policy(self.regressor, morton_order(base), np.asarray(scale, float), self.n_actuators,
                      {**self.info, "transferred_to_vertices": len(base)})

    def digest(self) -> str:
        return "sha256:" + hashlib.sha256(self.regressor).hexdigest()

    def save(self, path: str | Path) -> None:
        buf = io.BytesIO()
        np.savez(buf, regressor=np.frombuffer(self.regressor, dtype=np.uint8), order=self.order, scale=self.scale,
                 n_actuators=np.int64(self.n_actuators),
                 info=np.array(json.dumps({"format": POLICY_FORMAT, **self.info})))
        write_bytes(Path(path), buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> Policy:
        try:
            with np.load(path) as z:
                info = json.loads(str(z["info"]))
                if info.get("format") != POLICY_FORMAT:
                    raise ValueError(f"{path}: not a GEN-LAL policy file")
                return cls(regressor=z["regressor"].tobytes(), order=z["order"], scale=z["scale"],
                           n_actuators=int(z["n_actuators"]), info=info)
        except (OSError, KeyError) as exc:
            raise ValueError(f"{path}: cannot read a GEN-LAL policy ({exc})") from exc


def offset_scale(y: np.ndarray) -> np.ndarray:
    """Per-axis standard deviation (3,) of offsets (n, V, 3), metres: the fixed scale of the CNN's mesh input."""
    s = np.sqrt(np.asarray(y, np.float64).reshape(-1, 3).var(axis=0))
    return np.where(s > 1e-12, s, 1e-3)


def pool_digest(x: np.ndarray, y: np.ndarray) -> str:
    """SHA-256 of a policy pool's actuators and offsets: which data a policy was learned on."""
    h = hashlib.sha256(np.ascontiguousarray(x, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(y, dtype=np.float32).tobytes())
    return "sha256:" + h.hexdigest()


def _split_groups(runs: list[RunLabels]) -> list[tuple[RunLabels, RunLabels]]:
    """(training rows, held-out rows) pairs: leave one simulated run out; with a single run, leave one step out."""
    if len(runs) >= 2:
        return [(concat_runs([o for k, o in enumerate(runs) if k != r]), held) for r, held in enumerate(runs)]
    (run,) = runs
    pairs = []
    for n in np.unique(run.n_labelled):
        pairs.append((run.subset(run.n_labelled != n), run.subset(run.n_labelled == n)))
    return pairs


def heldout_fit(runs: list[RunLabels], settings: PolicySettings) -> list[dict]:
    """Held-out fit of the regressor (leave one simulated run out, or one step of a single run), per labelled-set
    size: R² of the ranked targets, rank correlation (Spearman) of predicted and measured reductions, and the
    measured reductions' mean and spread (%)."""
    if not runs or (len(runs) == 1 and len(np.unique(runs[0].n_labelled)) < 2):
        return []
    per: dict[int, dict[str, list[float]]] = {}
    for train, held in _split_groups(runs):
        reg = _fit(train, settings)
        pred = _predict(settings.model, reg, held.feats, held.cnn)
        for n in np.unique(held.n_labelled):
            m = held.n_labelled == n
            t, p = held.target[m], pred[m]
            ss = float(((t - t.mean()) ** 2).sum())
            pt = p - p.mean() + t.mean()  # a rank target: only the within-step order and scale matter
            rec = per.setdefault(int(n), {"r2": [], "spearman": [], "delta": []})
            rec["r2"].append(1.0 - float(((t - pt) ** 2).sum()) / ss if ss > 0 else 0.0)
            rec["spearman"].append(float(np.corrcoef(rank01(p), rank01(t))[0, 1]) if p.std() > 0 else 0.0)
            rec["delta"].extend((100 * held.delta[m]).tolist())
    return [{"n_labelled": n, "r2": float(np.mean(v["r2"])), "spearman": float(np.mean(v["spearman"])),
             "reduction_mean_pct": float(np.mean(v["delta"])), "reduction_sd_pct": float(np.std(v["delta"])),
             "n_candidates": len(v["delta"]), "held_out": "run" if len(runs) >= 2 else "step"}
            for n, v in sorted(per.items())]


def validation_curve(policy: Policy | None, x: np.ndarray, y: np.ndarray, settings: PolicySettings,
                     cfg: LearnerConfig, seed: int, clustered: np.ndarray | None = None) -> list[float]:
    """A short AL run on the validation part: its pseudo-test mean errors (µm) per step (``policy`` None: random);
    with a ``clustered`` mask it selects among the clustered rows and is judged on the i.i.d. rows."""
    rng = np.random.default_rng([settings.seed, seed, 0x7A1])
    test, pool = split_simulation(rng, len(x), clustered, settings.pseudo_test)
    lab = pool[:settings.init]
    errs = []
    while True:
        state = learner.fit(x[lab], y[lab], cfg)
        errs.append(1e6 * learner.mean_error(state, x[test], y[test]))
        cand = np.setdiff1d(pool, lab)
        if len(lab) >= settings.budget or len(cand) == 0:
            return errs
        b = min(settings.batch, settings.budget - len(lab), len(cand))
        pos = rng.choice(len(cand), size=b, replace=False) if policy is None else \
            policy.select(state, x[lab], y[lab], x[cand], b, cfg)
        lab = np.concatenate([lab, cand[pos]])


def learn_policy(x: np.ndarray, y: np.ndarray, base: np.ndarray, settings: PolicySettings, cfg: LearnerConfig,
                 work_dir: str | Path, log: Callable[[str], None] = print,
                 clustered: np.ndarray | None = None, workers: int = 1) -> Policy:
    """Algorithm 1 on the policy pool (x, y): simulated runs (checkpointed in ``work_dir``), the regressor, its
    held-out fit, and the selection setting chosen on the validation part. ``clustered`` marks the policy pool's
    clustered candidate rows (see :func:`offline.active.labels.split_simulation`). The simulated runs and the
    validation curves go to ``workers`` processes (each deterministic given its seed: the same policy)."""
    if settings.model not in MODELS:
        raise ValueError(f"unknown policy model {settings.model!r}; choose from {', '.join(MODELS)}")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    stamp = work / "pool.json"
    digest = pool_digest(x, y)
    if stamp.exists() and json.loads(stamp.read_text()).get("policy_pool_hash") != digest:
        raise ValueError(f"{work}: simulated runs of a different policy pool; use a new output folder")
    write_bytes(stamp, json.dumps({"policy_pool_hash": digest, "settings": asdict(settings)}).encode())
    perm = np.random.default_rng([settings.seed, 0x5A1]).permutation(len(x))
    n_val = round(settings.validation_fraction * len(x))
    sim, val = perm[n_val:], perm[:n_val]
    order, scale = morton_order(base), offset_scale(y)
    t0 = time.perf_counter()
    csim = None if clustered is None else clustered[sim]
    found: dict[int, RunLabels] = {}
    for tau in range(settings.n_runs):
        path = work / f"run_{tau:03d}.npz"
        if path.exists():
            found[tau] = RunLabels.load(path)
            log(f"policy: simulated run {tau + 1}/{settings.n_runs} loaded from {path}")
    args = (x[sim], y[sim], csim, settings, cfg, order, scale)
    for tau, run, seconds in _in_workers(_simulate, [(tau, *args) for tau in range(settings.n_runs)
                                                     if tau not in found], workers):
        run.save(work / f"run_{tau:03d}.npz")
        found[tau] = run
        log(f"policy: simulated run {tau + 1}/{settings.n_runs}: {len(run.delta)} candidates labelled in "
            f"{seconds:.0f} s (mean reduction {100 * run.delta.mean():.2f} %)")
    runs = [found[tau] for tau in range(settings.n_runs)]
    fit_stats = heldout_fit(runs, settings)
    for f in fit_stats:
        log(f"policy: held-out fit at {f['n_labelled']} labelled: R² {f['r2']:+.3f}, rank correlation "
            f"{f['spearman']:+.3f} (reduction {f['reduction_mean_pct']:+.2f} ± {f['reduction_sd_pct']:.2f} %)")
    rows = concat_runs(runs)
    info = {"model": settings.model, "committee": settings.committee, "settings": asdict(settings),
            "learner": asdict(cfg), "n_samples": len(rows.target), "policy_pool_hash": digest, "n_pool": len(x),
            "n_simulation": len(sim), "n_validation": len(val), "n_vertices": len(base), "heldout_fit": fit_stats}
    policy = Policy(_fit(rows, settings, log), order, scale, int(x.shape[1]), info)
    key, values = ("family", settings.family_sizes) if settings.label_mode == "batch" else \
        ("diversity", settings.diversity)
    info.update(labels=settings.label_mode, family=settings.family)
    cval = None if clustered is None else clustered[val]
    choices: dict[str, list[float]] | None = None
    best = values[0]
    if len(values) > 1:  # one value needs no choosing

        candidates: list[tuple[str, Policy | None]] = [("random", None)]
        candidates += [(str(v), policy.with_setting(key, v)) for v in values]
        jobs = [(name, pol, x[val], y[val], settings, cfg, s, cval) for name, pol in candidates
                for s in range(settings.validation_seeds)]
        choices = {name: [] for name, _ in candidates}
        for name, value in sorted(_in_workers(_validation_score, jobs, workers), key=lambda r: r[1]):
            choices[name].append(value[1])
        best = min(values, key=lambda v: np.mean(choices[str(v)]))
        log(f"policy: validation mean log error per {key}: " +
            ", ".join(f"{k} {np.mean(v):.4f}" for k, v in choices.items()) + f"; chose {best}")
    policy = policy.with_setting(key, best)
    policy.info["validated_setting"] = key
    policy.info.update({"validation_mean_log_error": choices, "seconds": round(time.perf_counter() - t0, 1)})
    log(f"policy: {settings.model} regressor on {len(rows.target)} labelled candidates ({policy.info['seconds']} s)")
    return policy


def _simulate(tau: int, x: np.ndarray, y: np.ndarray, clustered: np.ndarray | None, settings: PolicySettings,
              cfg: LearnerConfig, order: np.ndarray, scale: np.ndarray) -> tuple[int, RunLabels, float]:
    """Simulated run ``tau`` of Algorithm 1 on the simulation part; its labels and seconds."""
    t1 = time.perf_counter()
    run = simulate_batch_run(x, y, clustered, tau, settings.label_settings(), cfg) \
        if settings.label_mode == "batch" else \
        simulate_run(x, y, tau, settings.label_settings(), cfg, order, scale, clustered)
    return tau, run, time.perf_counter() - t1


def _validation_score(name: str, pol: Policy | None, x: np.ndarray, y: np.ndarray, settings: PolicySettings,
                      cfg: LearnerConfig, seed: int, clustered: np.ndarray | None) -> tuple[str, tuple[int, float]]:
    """Mean log pseudo-test error of a short simulated AL run with ``pol`` (None: random) on the validation part."""
    return name, (seed, float(np.mean(np.log(validation_curve(pol, x, y, settings, cfg, seed, clustered)))))


def _in_workers(fn: Callable[..., Any], jobs: list[tuple], workers: int) -> Iterator[Any]:
    """``fn(*job)`` for every job, in ``workers`` processes (one thread each) when there are several; results as
    they finish."""
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            yield fn(*job)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"),
                             initializer=_one_thread) as ex:
        for fut in as_completed([ex.submit(fn, *job) for job in jobs]):
            yield fut.result()


def _one_thread() -> None:
    """A policy worker process: one thread for torch and BLAS (the jobs are the parallelism)."""
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    _LIMITS.append(threadpool_limits(1))


_LIMITS: list[Any] = []
