"""Candidate batch families, their features, the batch-aware oracle, and clustered simulation pools."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.headspec import load_head
from offline.active import learner
from offline.active.batches import N_BATCH_FEATURES, batch_family, batch_features, family_seed
from offline.active.data import PoolSettings, clustered_candidates, clustered_policy_rows
from offline.active.labels import split_simulation
from offline.active.selectors import BASELINES, SelectionContext
from offline.active.uncertainty import committee, state_features
from offline.dataset.sampling import sample_poses
from offline.dataset.splits import assign_splits

ROOT = Path(__file__).resolve().parents[3]


def test_the_family_starts_with_the_farthest_point_batch_and_has_a_fixed_size(tiny, cfg):
    lab = np.arange(8)
    ctx = SelectionContext(x=tiny.pool.x, labelled=lab, candidates=np.arange(8, len(tiny.pool)),
                           y_labelled=tiny.pool.y[lab], state=None, batch=5, rng=np.random.default_rng(0),
                           config=cfg)
    xl, xc = tiny.pool.x[lab], tiny.pool.x[8:]
    scores = np.random.default_rng(1).random((len(xc), 3))
    fam = batch_family(scores, xl, xc, 5, 7, family_seed(8, 1))
    assert len(fam) == 7 and all(len(set(b.tolist())) == 5 for b in fam)
    np.testing.assert_array_equal(8 + fam[0], BASELINES["space_filling"](ctx))
    again = batch_family(scores, xl, xc, 5, 7, family_seed(8, 1))
    assert all(np.array_equal(a, b) for a, b in zip(fam, again, strict=True))  # seeded: the same family


def test_batch_features_see_a_spread_batch_as_spread_and_far(tiny, cfg):
    lab = np.arange(8)
    state = learner.fit(tiny.pool.x[lab], tiny.pool.y[lab], cfg)
    xl, xc = tiny.pool.x[lab], tiny.pool.x[8:]
    ranked = state_features(committee(state, xl, tiny.pool.y[lab], cfg, 2), xl, xc)
    d = np.sqrt(((xc[:, None] - xc[None]) ** 2).sum(-1))
    piled = np.argsort(d[0])[:5]  # candidate 0 and its four nearest neighbours
    fam = batch_family(ranked[:, :-1], xl, xc, 5, 1, family_seed(8))
    f = batch_features(ranked, xl, xc, [piled, fam[0]])
    assert f.shape == (2, N_BATCH_FEATURES)
    assert f[1, -2] > f[0, -2]  # the farthest-point batch is more spread than a pile
    assert f[1, 1] > f[0, 1] or f[1, 1] == 1.0  # and its members lie farther from the labelled poses
    assert np.allclose(f[:, -1], np.log(8))


def test_the_oracle_keeps_a_batch_no_worse_on_the_pool_than_the_farthest_point_batch(tiny, cfg):
    lab = np.arange(8)
    state = learner.fit(tiny.pool.x[lab], tiny.pool.y[lab], cfg)
    ctx = SelectionContext(x=tiny.pool.x, labelled=lab, candidates=np.arange(8, len(tiny.pool)),
                           y_labelled=tiny.pool.y[lab], state=state, batch=5, rng=np.random.default_rng(0),
                           config=cfg, oracle_y=tiny.pool.y)
    chosen = BASELINES["greedy"](ctx)
    far = BASELINES["space_filling"](ctx)

    def pool_error(batch):
        idx = np.concatenate([lab, batch])
        return learner.mean_error(learner.fit(tiny.pool.x[idx], tiny.pool.y[idx], cfg), tiny.pool.x, tiny.pool.y)

    assert pool_error(chosen) <= pool_error(far)


def test_a_clustered_simulation_pool_selects_among_clustered_rows_and_is_judged_on_the_rest():
    clustered = np.arange(30) % 3 != 0
    test, cand = split_simulation(np.random.default_rng(0), 30, clustered, 6)
    assert len(test) == 6 and not clustered[test].any()
    assert sorted(cand.tolist()) == np.flatnonzero(clustered).tolist()
    test, cand = split_simulation(np.random.default_rng(0), 30, None, 6)  # i.i.d. pool: one random partition
    assert len(test) == 6 and sorted(np.concatenate([test, cand]).tolist()) == list(range(30))


def test_the_clustered_pool_clusters_part_of_the_policy_pool_with_its_own_centres():
    head = load_head(ROOT / "heads" / "sample" / "head.toml")
    settings = PoolSettings(poses=600, clusters=8)
    samples = sample_poses(head, settings.poses, seed=settings.seed, boundary_prob=settings.boundary_prob)
    out = clustered_candidates(head, samples, settings)
    rows = clustered_policy_rows(len(samples), settings)
    split = assign_splits(len(samples), settings.seed)
    np.testing.assert_array_equal(out[split.test], samples[split.test])  # the test poses stay i.i.d.
    assert not np.isin(rows, split.test).any() and len(rows) > 0
    changed = np.flatnonzero((out != samples).any(axis=1))
    assert np.isin(rows, changed).all()
    lo, hi = out.min(axis=0), out.max(axis=0)
    x = (out[rows] - lo) / np.where(hi > lo, hi - lo, 1.0)
    nn = np.sort(np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1)), axis=1)[:, 1]
    xi = (samples[split.test] - lo) / np.where(hi > lo, hi - lo, 1.0)
    nn_iid = np.sort(np.sqrt(((xi[:, None] - xi[None]) ** 2).sum(-1)), axis=1)[:, 1]
    assert np.median(nn) < 0.5 * np.median(nn_iid)  # redundant: neighbours much closer than among i.i.d. poses
