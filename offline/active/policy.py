"""GEN-LAL: learn a selection policy from simulated AL runs (Algorithm 1) and select with it (Algorithm 2).

Learning (``learn_policy``): for each simulation configuration τ, a random partition of the labelled policy pool
gives a pseudo-test set, an initial labelled set and a simulated unlabelled pool. The simulated random AL run
(``simulate_run``, the paper's Algorithm 2) trains the predictor on the labelled set, and at every step records,
for candidates drawn at random from the simulated pool, the features (``offline.active.features``) and the
reduction of the pseudo-test error that adding that one candidate brings; then it adds a random batch and goes on.
A reduction is measured against a control: the current predictor fine-tuned for the same iterations on the
labelled set alone, so the gain of training longer is not credited to the candidate. Reductions are relative to the
control's error and centred per step (Algorithm 2 only ranks candidates of one state), then standardized; the CNN
regressor (``offline.active.regressor``) learns features → reduction.

Selection (``Policy.select``): predict the reduction of every pool candidate and take the top batch.

The paper adds one sample per simulated step; here the walk adds a batch per step (the benchmark's granularity)
and several candidates are measured per step, which covers labelled-set sizes up to the budget with far fewer
retrainings. Each simulated run is checkpointed to its own file, so a killed policy learning resumes.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from models.atomic import write_bytes
from offline.active import learner
from offline.active.features import CandidateFeatures, candidate_features, concat, morton_order
from offline.active.learner import KsnnState, LearnerConfig
from offline.active.regressor import predict_reduction, train_regressor

POLICY_FORMAT = "likeness-genlal-policy"


@dataclass(frozen=True)
class PolicySettings:
    """How the policy is learned: simulated runs, their sizes, candidates measured per step, regressor epochs."""

    n_runs: int = 6
    init: int = 10
    batch: int = 10
    budget: int = 100
    candidates_per_step: int = 12
    pseudo_test: int = 40
    epochs: int = 60
    seed: int = 0


def simulate_run(x: np.ndarray, y: np.ndarray, tau: int, settings: PolicySettings, cfg: LearnerConfig,
                 order: np.ndarray, scale: np.ndarray) -> tuple[CandidateFeatures, np.ndarray, np.ndarray]:
    """One simulated random AL run on the policy pool (x, y) for configuration ``tau``.

    Returns the candidates' features, their relative pseudo-test error reductions and the step each belongs to.
    """
    rng = np.random.default_rng([settings.seed, tau, 0x1A1])
    perm = rng.permutation(len(x))
    n_test = min(settings.pseudo_test, len(x) // 3)
    test, rest = perm[:n_test], perm[n_test:]
    labelled = list(rest[:settings.init])
    unlabelled = list(rest[settings.init:])
    feats: list[CandidateFeatures] = []
    deltas: list[np.ndarray] = []
    steps: list[np.ndarray] = []
    step = 0
    while len(labelled) < settings.budget and len(unlabelled) > settings.candidates_per_step:
        lab = np.asarray(labelled)
        state = learner.fit(x[lab], y[lab], cfg, seed=cfg.seed + tau)
        control = learner.mean_error(learner.fine_tune(state, x[lab], y[lab], cfg), x[test], y[test])
        cand = rng.choice(np.asarray(unlabelled), size=settings.candidates_per_step, replace=False)
        delta = np.empty(len(cand))
        for j, c in enumerate(cand):
            idx = np.append(lab, c)
            delta[j] = (control - learner.mean_error(learner.fine_tune(state, x[idx], y[idx], cfg),
                                                     x[test], y[test])) / control
        feats.append(candidate_features(state, x[lab], x[cand], order, scale))
        deltas.append(delta)
        steps.append(np.full(len(cand), step))
        add = rng.choice(np.asarray(unlabelled), size=min(settings.batch, len(unlabelled)), replace=False)
        labelled.extend(int(a) for a in add)
        added = set(add.tolist())
        unlabelled = [u for u in unlabelled if u not in added]
        step += 1
    return concat(feats), np.concatenate(deltas), np.concatenate(steps)


@dataclass
class Policy:
    """A learned GEN-LAL policy: the regressor's state, the vertex order and offset scale its features use."""

    regressor: bytes
    order: np.ndarray
    scale: np.ndarray
    n_actuators: int
    info: dict

    def scores(self, state: KsnnState, x_labelled: np.ndarray, x_cand: np.ndarray) -> np.ndarray:
        """Predicted error reduction of each candidate (higher is better)."""
        if len(self.order) != state.W2.shape[2]:
            raise ValueError(f"policy learned on {len(self.order)} vertices; the predictor has {state.W2.shape[2]} "
                             "(give the policy the base surface of this mesh with Policy.for_mesh)")
        return predict_reduction(self.regressor, candidate_features(state, x_labelled, x_cand, self.order,
                                                                    self.scale))

    def select(self, state: KsnnState, x_labelled: np.ndarray, x_cand: np.ndarray, batch: int) -> np.ndarray:
        """Algorithm 2: positions in ``x_cand`` of the ``batch`` candidates with the largest predicted reduction."""
        s = self.scores(state, x_labelled, x_cand)
        return np.argsort(-s, kind="stable")[:batch]

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


def learn_policy(x: np.ndarray, y: np.ndarray, base: np.ndarray, settings: PolicySettings, cfg: LearnerConfig,
                 work_dir: str | Path, log: Callable[[str], None] = print) -> Policy:
    """Algorithm 1 on the policy pool (x, y): simulated runs (checkpointed in ``work_dir``), then the regressor."""
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    stamp = work / "pool.json"
    digest = pool_digest(x, y)
    if stamp.exists() and json.loads(stamp.read_text()).get("policy_pool_hash") != digest:
        raise ValueError(f"{work}: simulated runs of a different policy pool; use a new output folder")
    write_bytes(stamp, json.dumps({"policy_pool_hash": digest, "settings": asdict(settings)}).encode())
    order = morton_order(base)
    scale = offset_scale(y)
    parts: list[CandidateFeatures] = []
    targets: list[np.ndarray] = []
    t0 = time.perf_counter()
    for tau in range(settings.n_runs):
        path = work / f"run_{tau:03d}.npz"
        if path.exists():
            with np.load(path) as z:
                f = CandidateFeatures(mesh=z["mesh"], act=z["act"], extra=z["extra"])
                delta, step = z["delta"], z["step"]
            log(f"policy: simulated run {tau + 1}/{settings.n_runs} loaded from {path}")
        else:
            t1 = time.perf_counter()
            f, delta, step = simulate_run(x, y, tau, settings, cfg, order, scale)
            buf = io.BytesIO()
            np.savez(buf, mesh=f.mesh, act=f.act, extra=f.extra, delta=delta, step=step)
            write_bytes(path, buf.getvalue())
            log(f"policy: simulated run {tau + 1}/{settings.n_runs}: {len(delta)} candidates measured in "
                f"{time.perf_counter() - t1:.0f} s (mean reduction {100 * delta.mean():.2f} %)")
        centred = delta.copy()
        for s in np.unique(step):
            centred[step == s] -= delta[step == s].mean()
        parts.append(f)
        targets.append(centred)
    feats = concat(parts)
    target = np.concatenate(targets)
    std = float(target.std()) or 1.0
    regressor = train_regressor(feats, target / std, epochs=settings.epochs, seed=settings.seed, log=log)
    info = {"settings": asdict(settings), "learner": asdict(cfg), "n_samples": len(target),
            "policy_pool_hash": pool_digest(x, y),
            "n_pool": len(x), "n_vertices": len(base), "seconds": round(time.perf_counter() - t0, 1)}
    log(f"policy: regressor trained on {len(target)} measured candidates ({info['seconds']} s in all)")
    return Policy(regressor=regressor, order=order, scale=scale, n_actuators=int(x.shape[1]), info=info)
