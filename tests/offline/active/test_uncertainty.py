"""GEN-LAL's uncertainty features: ranks, and a committee that disagrees more far from the labelled poses."""

from __future__ import annotations

import numpy as np

from offline.active import learner
from offline.active.uncertainty import N_FEATURES, NAMES, committee, rank01, raw_features, state_features


def test_rank01_scales_ranks_to_the_unit_interval_and_averages_ties():
    np.testing.assert_allclose(rank01(np.array([3.0, 1.0, 2.0])), [1.0, 0.0, 0.5])
    np.testing.assert_allclose(rank01(np.array([1.0, 1.0, 2.0])), [0.25, 0.25, 1.0])
    np.testing.assert_allclose(rank01(np.array([7.0])), [0.5])


def test_candidates_far_from_the_labelled_poses_rank_high_on_distance_and_disagreement(tiny, cfg):
    lab = np.argsort(tiny.pool.x[:, 0])[:20]  # labelled poses all at small values of actuator 0
    x_lab, y_lab = tiny.pool.x[lab], tiny.pool.y[lab]
    state = learner.fit(x_lab, y_lab, cfg)
    members = committee(state, x_lab, y_lab, cfg, 3)
    assert members[0] is state and len(members) == 3
    x_cand = tiny.test.x
    raw = raw_features(members, x_lab, x_cand)
    far = x_cand[:, 0] > 0.7
    near = x_cand[:, 0] < 0.3
    col = {n: j for j, n in enumerate(NAMES)}
    assert raw[far, col["nearest"]].mean() > raw[near, col["nearest"]].mean()
    assert raw[far, col["disagreement"]].mean() > raw[near, col["disagreement"]].mean()
    f = state_features(members, x_lab, x_cand)
    assert f.shape == (len(x_cand), N_FEATURES) and f[:, :-1].min() >= 0 and f[:, :-1].max() <= 1
    np.testing.assert_allclose(f[:, -1], np.log(len(x_lab)))
