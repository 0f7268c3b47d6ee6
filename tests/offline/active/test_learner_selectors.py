"""The AL predictor and the selection rules: valid batches, bmdal-reg's network matches the KSNN, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from offline.active import learner
from offline.active.selectors import BASELINES, SelectionContext, scalar_network


def context(tiny, cfg, name: str, n_lab: int = 8, batch: int = 5, seed: int = 0) -> SelectionContext:
    lab = np.arange(n_lab)
    state = learner.fit(tiny.pool.x[lab], tiny.pool.y[lab], cfg)
    return SelectionContext(x=tiny.pool.x, labelled=lab, candidates=np.arange(n_lab, len(tiny.pool)),
                            y_labelled=tiny.pool.y[lab], state=state, batch=batch,
                            rng=np.random.default_rng(seed), config=cfg,
                            oracle_y=tiny.pool.y if name == "greedy" else None)


def test_training_is_deterministic_and_more_data_lowers_the_test_error(tiny, cfg):
    a = learner.fit(tiny.pool.x[:10], tiny.pool.y[:10], cfg)
    b = learner.fit(tiny.pool.x[:10], tiny.pool.y[:10], cfg)
    assert np.array_equal(learner.predict(a, tiny.test.x), learner.predict(b, tiny.test.x))
    big = learner.fit(tiny.pool.x, tiny.pool.y, cfg)
    e_small = learner.errors(a, tiny.test.x, tiny.test.y)["mean_euclidean_um"]
    e_big = learner.errors(big, tiny.test.x, tiny.test.y)["mean_euclidean_um"]
    assert e_big < 0.7 * e_small


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_every_baseline_returns_a_batch_of_distinct_candidates(tiny, cfg, name):
    ctx = context(tiny, cfg, name)
    chosen = np.asarray(BASELINES[name](ctx))
    assert len(chosen) == ctx.batch and len(np.unique(chosen)) == ctx.batch
    assert np.isin(chosen, ctx.candidates).all()


def test_greedy_refuses_to_run_without_the_labels():
    ctx = SelectionContext(x=np.zeros((3, 2)), labelled=np.array([0]), candidates=np.array([1, 2]),
                           y_labelled=np.zeros((1, 2, 3)), state=None, batch=1, rng=np.random.default_rng(0),
                           config=learner.LearnerConfig())
    with pytest.raises(ValueError, match="pool label"):
        BASELINES["greedy"](ctx)


def test_space_filling_picks_the_candidate_farthest_from_the_labelled_set(tiny, cfg):
    ctx = context(tiny, cfg, "space_filling", batch=1)
    d = np.sqrt(((tiny.pool.x[ctx.candidates][:, None] - tiny.pool.x[ctx.labelled][None]) ** 2).sum(-1)).min(1)
    assert BASELINES["space_filling"](ctx)[0] == ctx.candidates[np.argmax(d)]


def test_the_network_given_to_bmdal_is_the_ksnn_projected_on_its_first_principal_direction(tiny, cfg):
    import torch

    lab = np.arange(12)
    state = learner.fit(tiny.pool.x[lab], tiny.pool.y[lab], cfg)
    net = scalar_network(state, tiny.pool.y[lab])
    with torch.no_grad():
        out = net(torch.from_numpy(tiny.test.x.astype(np.float32))).numpy()[:, 0]
    y = tiny.pool.y[lab] / state.scale
    u = np.linalg.svd((y - y.mean(0)).reshape(len(y), -1), full_matrices=False)[2][0]
    ref = (learner.predict(state, tiny.test.x) / state.scale).reshape(len(tiny.test.x), -1) @ u
    np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-3 * np.abs(ref).max())
