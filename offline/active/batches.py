"""Candidate batches and their features: what the batch-level GEN-LAL policy and the look-ahead oracle choose among.

A redundant (clustered) candidate pool rewards batches that cover the range of use, and whether a batch helps
depends on its members together, not one by one. So both the learned policy and the fully informed oracle choose
among a small *family* of whole batches, each built greedily by :func:`diverse_batch` from a per-candidate score
and a diversity weight: member 0 is the plain farthest-point batch (what space-filling picks), the next ones mix
the score with the weights in ``LAMBDAS``, and the rest draw a random score mixture and weight from a seeded
generator. The family is a function of the state, the candidates and the generator's seed only.

Batch features (:func:`batch_features`) summarize a batch for the policy's regressor: the mean over its members of
each ranked candidate feature (``offline.active.uncertainty.NAMES``), the smallest member rank on distance to the
labelled set, the batch's own spread (mean nearest-neighbour distance among labelled and chosen poses, over the
candidates' median distance to the labelled set) and the log labelled-set size.
"""

from __future__ import annotations

import numpy as np

from offline.active.uncertainty import NAMES, rank01

#: Diversity weights of the family's fixed members (after the plain farthest-point batch).
LAMBDAS = (8.0, 2.0, 0.5)
#: A weight this large makes :func:`diverse_batch` a farthest-point batch (the score breaks ties only).
FARTHEST = 1e6
N_BATCH_FEATURES = len(NAMES) + 3


def nearest_distance(x_cand: np.ndarray, x_lab: np.ndarray) -> np.ndarray:
    """Distance (n,) from every candidate to its nearest labelled pose (chunked; inf without labelled poses)."""
    d = np.full(len(x_cand), np.inf)
    for k in range(0, len(x_lab), 256):
        d = np.minimum(d, np.sqrt(((x_cand[:, None, :] - x_lab[None, k:k + 256, :]) ** 2).sum(-1)).min(axis=1))
    return d


def diverse_batch(scores: np.ndarray, x_lab: np.ndarray, x_cand: np.ndarray, batch: int,
                  diversity: float) -> np.ndarray:
    """Greedy batch: each pick maximizes rank(score) + diversity × distance to labelled and chosen / its median."""
    s = rank01(np.asarray(scores, np.float64))
    d = nearest_distance(x_cand, x_lab)
    if not np.isfinite(d).all():
        d = np.ones(len(x_cand))
    med = float(np.median(d)) or 1.0
    chosen: list[int] = []
    for _ in range(min(batch, len(x_cand))):
        v = s + diversity * d / med
        v[chosen] = -np.inf
        j = int(np.argmax(v))
        chosen.append(j)
        d = np.minimum(d, np.sqrt(((x_cand - x_cand[j]) ** 2).sum(-1)))
    return np.asarray(chosen, dtype=np.int64)


def batch_family(feats: np.ndarray, x_lab: np.ndarray, x_cand: np.ndarray, batch: int, size: int,
                 rng: np.random.Generator) -> list[np.ndarray]:
    """``size`` candidate batches (positions in ``x_cand``) from per-candidate score columns ``feats`` (n, k).

    Member 0: farthest-point; then ``feats[:, 0]`` with each weight of ``LAMBDAS``; then random mixtures of the
    columns with log-uniform weights in [0.5, 20]. Duplicate batches are kept (the family's size is fixed)."""
    feats = np.asarray(feats, np.float64).reshape(len(x_cand), -1)
    out = [diverse_batch(np.zeros(len(x_cand)), x_lab, x_cand, batch, FARTHEST)]
    for lam in LAMBDAS:
        if len(out) >= size:
            break
        out.append(diverse_batch(feats[:, 0], x_lab, x_cand, batch, lam))
    while len(out) < size:
        w = rng.normal(size=feats.shape[1])
        lam = float(np.exp(rng.uniform(np.log(0.5), np.log(20.0))))
        out.append(diverse_batch(feats @ w, x_lab, x_cand, batch, lam))
    return out[:max(size, 1)]


def batch_features(ranked: np.ndarray, x_lab: np.ndarray, x_cand: np.ndarray, batches: list[np.ndarray]
                   ) -> np.ndarray:
    """Features (n_batches, N_BATCH_FEATURES) of each batch from the candidates' ranked features ``ranked``
    (n, len(NAMES) + 1: the ranks, then log n_labelled), see the module text."""
    k = len(NAMES)
    med = float(np.median(nearest_distance(x_cand, x_lab))) if len(x_lab) else 1.0
    med = med if np.isfinite(med) and med > 0 else 1.0
    rows = []
    for b in batches:
        xb = x_cand[b]
        pts = np.concatenate([x_lab, xb])
        d = np.sqrt(((xb[:, None, :] - pts[None, :, :]) ** 2).sum(-1))
        d[np.arange(len(b)), len(x_lab) + np.arange(len(b))] = np.inf
        spread = float(d.min(axis=1).mean()) / med if len(pts) > 1 else 0.0
        rows.append(np.concatenate([ranked[b, :k].mean(axis=0), [ranked[b, 1].min(), spread, ranked[b[0], k]]]))
    return np.asarray(rows, dtype=np.float64)


def family_seed(n_labelled: int, *extra: int) -> np.random.Generator:
    """The generator of one step's family: fixed by the labelled-set size and the caller's integers."""
    return np.random.default_rng([0xBA7C, int(n_labelled), *[int(e) for e in extra]])


__all__ = ["FARTHEST", "LAMBDAS", "N_BATCH_FEATURES", "batch_family", "batch_features", "diverse_batch",
           "family_seed", "nearest_distance", "rank01"]
