"""GEN-LAL's state features of candidate poses: what the current predictor does not know about each of them.

The paper's model state (the mesh the predictor yields for a candidate) is a function of the candidate's actuator
values and carries no uncertainty. These features do, as the original LAL's model-state features do for
classifiers: computed from a small committee of predictors trained from scratch with the benchmark's own schedule
on the labelled set (member 0 is the benchmark's predictor itself, the others differ only in their seed), they
are, per candidate,

- ``disagreement``: mean over the surface of the committee's per-vertex spread (Euclidean norm of the std);
- ``nearest``: distance to the nearest labelled pose (normalized actuator space);
- ``knn``: mean distance to the 5 nearest labelled poses;
- ``pred_mean`` / ``pred_max``: mean and largest predicted offset norm (how far the skin is strained);
- ``ends``: share of the actuators at a range end (within 2 %);
- ``crowding``: mean distance to the 10 nearest other candidates (low: a dense, representative region).

Each feature is turned into its rank among the candidates of the same step (0..1), so one regressor serves every
labelled-set size and skin; the log labelled-set size joins them as the only absolute quantity.
"""

from __future__ import annotations

import numpy as np

from offline.active import learner
from offline.active.learner import KsnnState, LearnerConfig

NAMES = ("disagreement", "nearest", "knn", "pred_mean", "pred_max", "ends", "crowding")
N_FEATURES = len(NAMES) + 1  # the ranks, then log n_labelled


def committee(state: KsnnState, x_lab: np.ndarray, y_lab: np.ndarray, cfg: LearnerConfig,
              members: int) -> list[KsnnState]:
    """``state`` (seed ``cfg.seed``) and ``members - 1`` more predictors trained from scratch with other seeds."""
    return [state] + [learner.fit(x_lab, y_lab, cfg, seed=cfg.seed + 7919 * (m + 1)) for m in range(members - 1)]


def _min_dists(a: np.ndarray, b: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` smallest distances (n_a, k) from each row of ``a`` to the rows of ``b`` (chunked)."""
    out = []
    for s in range(0, len(a), 512):
        d = np.sqrt(np.maximum(((a[s:s + 512, None, :] - b[None, :, :]) ** 2).sum(-1), 0.0))
        kk = min(k, d.shape[1])
        out.append(np.sort(np.partition(d, kk - 1, axis=1)[:, :kk], axis=1))
    return np.concatenate(out)


def raw_features(states: list[KsnnState], x_lab: np.ndarray, x_cand: np.ndarray) -> np.ndarray:
    """The features of ``NAMES`` (n, 7) before ranking."""
    preds = np.stack([learner.predict(s, x_cand) for s in states])  # (M, n, V, 3)
    disagreement = np.linalg.norm(preds.std(axis=0), axis=2).mean(axis=1) if len(states) > 1 \
        else np.zeros(len(x_cand))
    norms = np.linalg.norm(preds[0], axis=2)
    d_lab = _min_dists(x_cand, x_lab, 5)
    ends = ((x_cand < 0.02) | (x_cand > 0.98)).mean(axis=1)
    crowd = _min_dists(x_cand, x_cand, 11)[:, 1:].mean(axis=1) if len(x_cand) > 1 else np.zeros(len(x_cand))
    return np.stack([disagreement, d_lab[:, 0], d_lab.mean(axis=1), norms.mean(axis=1), norms.max(axis=1), ends,
                     crowd], axis=1)


def rank01(v: np.ndarray) -> np.ndarray:
    """Ranks of ``v`` scaled to [0, 1] (ties averaged); 0.5 for a single value."""
    if len(v) < 2:
        return np.full(len(v), 0.5)
    order = np.argsort(v, kind="stable")
    r = np.empty(len(v))
    r[order] = np.arange(len(v), dtype=float)
    _, inv, counts = np.unique(v, return_inverse=True, return_counts=True)
    if (counts > 1).any():
        sums = np.bincount(inv, weights=r)
        r = sums[inv] / counts[inv]
    return r / (len(v) - 1)


def state_features(states: list[KsnnState], x_lab: np.ndarray, x_cand: np.ndarray) -> np.ndarray:
    """Ranked features of the candidates of one step plus log n_labelled: (n, N_FEATURES), float32."""
    raw = raw_features(states, x_lab, x_cand)
    ranked = np.stack([rank01(raw[:, j]) for j in range(raw.shape[1])], axis=1)
    logn = np.full((len(x_cand), 1), np.log(len(x_lab)))
    return np.concatenate([ranked, logn], axis=1).astype(np.float32)
