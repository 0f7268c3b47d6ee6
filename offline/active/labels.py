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


def simulate_run(x: np.ndarray, y: np.ndarray, tau: int, s: LabelSettings, cfg: LearnerConfig, order: np.ndarray,
                 scale: np.ndarray) -> RunLabels:
    """One simulated random AL run on (x, y) for configuration ``tau``, labelled from scratch."""
    rng = np.random.default_rng([s.seed, tau, 0x1A2])
    perm = rng.permutation(len(x))
    n_test = min(s.pseudo_test, len(x) // 3)
    test, rest = perm[:n_test], perm[n_test:]
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
