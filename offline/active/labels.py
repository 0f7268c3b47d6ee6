"""GEN-LAL's training data: simulated random AL runs on the policy pool (the paper's Algorithm 2), labelled with the
benchmark's own training protocol.

For each simulation configuration τ a random partition of the simulation pool gives a pseudo-test set, an initial
labelled set and a simulated unlabelled pool. At every step of a random walk up to the budget, candidates drawn from
the simulated pool are labelled with the reduction of the pseudo-test mean Euclidean error that adding that one
candidate brings when the predictor is retrained **from scratch with the benchmark's schedule** (what the benchmark
and the in-the-loop selection do after every batch), relative to the error without it, **averaged over several
training seeds** (paired: the same seeds with and without the candidate). The walk then adds a random batch.

Targets are ranked within their step (0..1, centred): Algorithm 2 only ranks the candidates of one state, and a
per-step rank gives every labelled-set size the same weight in the regressor's loss. Each run is checkpointed to
its own file, so a killed policy learning resumes.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.atomic import write_bytes
from offline.active import learner
from offline.active.features import CandidateFeatures, candidate_features
from offline.active.learner import LearnerConfig
from offline.active.uncertainty import committee, rank01, state_features


@dataclass(frozen=True)
class LabelSettings:
    """Sizes of the simulated runs: walk schedule, candidates labelled per step, seeds each label averages."""

    init: int = 10
    batch: int = 10
    budget: int = 100
    candidates_per_step: int = 12
    pseudo_test: int = 150
    label_seeds: int = 2
    committee: int = 3
    seed: int = 0
    family: int = 12  # batch labels: candidate batches labelled per step


@dataclass
class RunLabels:
    """One simulated run: per labelled candidate its features (both kinds), raw reduction, ranked target, step."""

    feats: np.ndarray  # (n, N_FEATURES) ranked uncertainty features
    cnn: CandidateFeatures  # the paper's CNN input (predicted mesh, actuators, two scalars)
    delta: np.ndarray  # relative pseudo-test error reduction, mean over label seeds
    target: np.ndarray  # rank of delta within its step, centred (-0.5..0.5)
    n_labelled: np.ndarray  # labelled-set size of the candidate's step

    def subset(self, m: np.ndarray) -> RunLabels:
        """The rows selected by mask or index ``m``."""
        return RunLabels(self.feats[m], CandidateFeatures(self.cnn.mesh[m], self.cnn.act[m], self.cnn.extra[m]),
                         self.delta[m], self.target[m], self.n_labelled[m])

    def save(self, path: Path) -> None:
        buf = io.BytesIO()
        np.savez(buf, feats=self.feats, mesh=self.cnn.mesh, act=self.cnn.act, extra=self.cnn.extra, delta=self.delta,
                 target=self.target, n_labelled=self.n_labelled)
        write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: Path) -> RunLabels:
        with np.load(path) as z:
            return cls(z["feats"], CandidateFeatures(z["mesh"], z["act"], z["extra"]), z["delta"], z["target"],
                       z["n_labelled"])


def concat_runs(runs: list[RunLabels]) -> RunLabels:
    """All runs' rows in one."""
    return RunLabels(np.concatenate([r.feats for r in runs]),
                     CandidateFeatures(np.concatenate([r.cnn.mesh for r in runs]),
                                       np.concatenate([r.cnn.act for r in runs]),
                                       np.concatenate([r.cnn.extra for r in runs])),
                     np.concatenate([r.delta for r in runs]), np.concatenate([r.target for r in runs]),
                     np.concatenate([r.n_labelled for r in runs]))


def split_simulation(rng: np.random.Generator, n: int, clustered: np.ndarray | None,
                     pseudo_test: int) -> tuple[np.ndarray, np.ndarray]:
    """(pseudo-test rows, shuffled candidate rows) of a simulation pool of ``n`` rows: with a ``clustered`` mask the
    pseudo-test rows are drawn from the i.i.d. rows and the candidates are the clustered rows (the benchmark's
    situation: select among redundant poses, be judged on the range of use); without, one random partition."""
    if clustered is None or not clustered.any() or clustered.all():
        perm = rng.permutation(n)
        n_test = min(pseudo_test, n // 3)
        return perm[:n_test], perm[n_test:]
    iid = rng.permutation(np.flatnonzero(~clustered))
    return iid[:pseudo_test], rng.permutation(np.flatnonzero(clustered))


def _empty_cnn(n: int) -> CandidateFeatures:
    return CandidateFeatures(np.zeros((n, 3, 0), np.float32), np.zeros((n, 0), np.float32),
                             np.zeros((n, 0), np.float32))


def simulate_batch_run(x: np.ndarray, y: np.ndarray, clustered: np.ndarray | None, tau: int, s: LabelSettings,
                       cfg: LearnerConfig) -> RunLabels:
    """One simulated AL run labelled per **batch**: at each step the family of candidate batches
    (``offline.active.batches``) is built from the committee's ranked features, every batch labelled with the
    pseudo-test error reduction of the predictor retrained from scratch with it (mean over the label seeds); the
    walk then adds one family member drawn at random, so the states resemble those the policy meets."""
    from offline.active.batches import batch_family, batch_features, family_seed

    rng = np.random.default_rng([s.seed, tau, 0x1A3])
    test, rest = split_simulation(rng, len(x), clustered, s.pseudo_test)
    labelled, unlabelled = list(rest[:s.init]), np.asarray(rest[s.init:])
    run_cfg = LearnerConfig(**{**cfg.__dict__, "seed": cfg.seed + tau})
    feats, deltas, targets, sizes = [], [], [], []
    while len(labelled) < s.budget and len(unlabelled) > s.batch:
        lab = np.asarray(labelled)
        state = learner.fit(x[lab], y[lab], run_cfg)
        members = committee(state, x[lab], y[lab], run_cfg, max(s.committee, s.label_seeds))
        control = [learner.mean_error(m, x[test], y[test]) for m in members[:s.label_seeds]]
        ranked = state_features(members[:s.committee], x[lab], x[unlabelled])
        b = min(s.batch, s.budget - len(lab))
        fam = batch_family(ranked[:, :-1], x[lab], x[unlabelled], b, s.family, family_seed(len(lab), s.seed, tau))
        delta = np.zeros(len(fam))
        for j, pos in enumerate(fam):
            idx = np.concatenate([lab, unlabelled[pos]])
            for k in range(s.label_seeds):
                fitted = learner.fit(x[idx], y[idx], run_cfg, seed=run_cfg.seed + (7919 * k if k else 0))
                delta[j] += (control[k] - learner.mean_error(fitted, x[test], y[test])) / control[k] / s.label_seeds
        feats.append(batch_features(ranked, x[lab], x[unlabelled], fam))
        deltas.append(delta)
        targets.append(rank01(delta) - 0.5)
        sizes.append(np.full(len(fam), len(lab)))
        walk = fam[int(rng.integers(len(fam)))]
        labelled.extend(int(a) for a in unlabelled[walk])
        unlabelled = np.delete(unlabelled, walk)
    n = sum(len(d) for d in deltas)
    return RunLabels(np.concatenate(feats), _empty_cnn(n), np.concatenate(deltas), np.concatenate(targets),
                     np.concatenate(sizes))


def simulate_run(x: np.ndarray, y: np.ndarray, tau: int, s: LabelSettings, cfg: LearnerConfig, order: np.ndarray,
                 scale: np.ndarray, clustered: np.ndarray | None = None) -> RunLabels:
    """One simulated random AL run on (x, y) for configuration ``tau``, labelled per candidate from scratch."""
    rng = np.random.default_rng([s.seed, tau, 0x1A2])
    test, rest = split_simulation(rng, len(x), clustered, s.pseudo_test)
    labelled = list(rest[:s.init])
    unlabelled = np.asarray(rest[s.init:])
    feats, cnn, deltas, targets, sizes = [], [], [], [], []
    members_n = max(s.committee, s.label_seeds)
    while len(labelled) < s.budget and len(unlabelled) > s.candidates_per_step:
        lab = np.asarray(labelled)
        run_cfg = LearnerConfig(**{**cfg.__dict__, "seed": cfg.seed + tau})
        state = learner.fit(x[lab], y[lab], run_cfg)
        members = committee(state, x[lab], y[lab], run_cfg, members_n)
        control = [learner.mean_error(m, x[test], y[test]) for m in members[:s.label_seeds]]
        pick = rng.choice(len(unlabelled), size=s.candidates_per_step, replace=False)
        cand = unlabelled[pick]
        delta = np.zeros(len(cand))
        for j, c in enumerate(cand):
            idx = np.append(lab, c)
            for k in range(s.label_seeds):
                seed = run_cfg.seed + (7919 * k if k else 0)
                err = learner.mean_error(learner.fit(x[idx], y[idx], run_cfg, seed=seed), x[test], y[test])
                delta[j] += (control[k] - err) / control[k] / s.label_seeds
        # features ranked among the whole simulated pool, as at selection time among the whole candidate pool
        feats.append(state_features(members[:s.committee], x[lab], x[unlabelled])[pick])
        cnn.append(candidate_features(state, x[lab], x[cand], order, scale))
        deltas.append(delta)
        targets.append(rank01(delta) - 0.5)
        sizes.append(np.full(len(cand), len(lab)))
        add = rng.choice(len(unlabelled), size=min(s.batch, len(unlabelled)), replace=False)
        labelled.extend(int(a) for a in unlabelled[add])
        unlabelled = np.delete(unlabelled, add)
    return RunLabels(np.concatenate(feats),
                     CandidateFeatures(np.concatenate([c.mesh for c in cnn]), np.concatenate([c.act for c in cnn]),
                                       np.concatenate([c.extra for c in cnn])),
                     np.concatenate(deltas), np.concatenate(targets), np.concatenate(sizes))
