"""GEN-LAL's policy (learning resumes, save and load, other meshes) and the selection loop that grows a dataset."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from offline.active import learner
from offline.active.batches import N_BATCH_FEATURES, batch_family, family_seed
from offline.active.features import morton_order
from offline.active.loop import grow_dataset
from offline.active.policy import Policy, PolicySettings, diverse_batch, learn_policy
from offline.active.uncertainty import committee, state_features
from offline.dataset.sampling import sample_poses, sample_ranges
from offline.dataset.store import PoseDataset
from offline.dataset.synthetic import SyntheticSpec
from offline.engine import SerialEngine

ROOT = Path(__file__).resolve().parents[3]
SMALL = PolicySettings(n_runs=2, init=5, batch=5, budget=15, candidates_per_step=4, pseudo_test=8, epochs=3,
                       committee=2, diversity=(0.0, 1.0), validation_seeds=1, family=4, family_sizes=(1, 4))
CNN = PolicySettings(**{**SMALL.__dict__, "model": "cnn", "diversity": (0.0,)})
CANDIDATE = PolicySettings(**{**SMALL.__dict__, "labels": "candidate"})


@pytest.fixture(scope="module")
def policy(tiny, cfg, tmp_path_factory) -> Policy:
    work = tmp_path_factory.mktemp("policy")
    return learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, SMALL, cfg, work, log=lambda m: None)


def test_a_policy_learned_in_two_worker_processes_is_the_one_learned_in_one(tiny, cfg, policy, tmp_path):
    """Simulated runs and validation curves spread over two processes: the same labels, regressor and choice."""
    two = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, SMALL, cfg, tmp_path, log=lambda m: None, workers=2)
    assert sorted(p.name for p in tmp_path.glob("run_*.npz")) == ["run_000.npz", "run_001.npz"]
    np.testing.assert_allclose(np.frombuffer(two.regressor, np.float64), np.frombuffer(policy.regressor, np.float64),
                               rtol=1e-7, atol=1e-9)
    assert two.family == policy.family
    got, want = two.info["validation_mean_log_error"], policy.info["validation_mean_log_error"]
    assert got.keys() == want.keys() and all(got[k] == pytest.approx(want[k], rel=1e-9) for k in want)


def test_morton_order_is_a_permutation_that_keeps_neighbours_close():
    g = np.stack(np.meshgrid(np.arange(16.0), np.arange(16.0), indexing="ij"), -1).reshape(-1, 2)
    pts = np.c_[g, np.zeros(len(g))]
    order = morton_order(pts)
    assert sorted(order) == list(range(len(pts)))
    steps = np.linalg.norm(np.diff(pts[order], axis=0), axis=1)
    shuffled = np.linalg.norm(np.diff(pts[np.random.default_rng(0).permutation(len(pts))], axis=0), axis=1)
    assert np.median(steps) == 1.0 and steps.mean() < 0.3 * shuffled.mean()


def test_policy_learning_resumes_from_its_simulated_runs_and_the_policy_survives_a_round_trip(tiny, cfg, policy,
                                                                                              tmp_path):
    work = tmp_path / "runs"
    one = PolicySettings(**{**SMALL.__dict__, "family_sizes": (4,)})  # no validation runs: only resuming is tested
    first = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, one, cfg, work, log=lambda m: None)
    (work / "run_001.npz").unlink()  # as if killed during the second simulated run
    messages: list[str] = []
    again = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, one, cfg, work, log=messages.append)
    assert any("1/2 loaded" in m for m in messages) and not any("2/2 loaded" in m for m in messages)
    assert again.regressor == first.regressor and again.family == 4  # the recomputed run is identical
    policy.save(tmp_path / "p.npz")
    back = Policy.load(tmp_path / "p.npz")
    state = learner.fit(tiny.pool.x[:10], tiny.pool.y[:10], cfg)
    args = (state, tiny.pool.x[:10], tiny.pool.y[:10], tiny.pool.x[10:], 5, cfg)
    np.testing.assert_array_equal(back.select(*args), policy.select(*args))
    assert back.label_mode == "batch" and back.info["validated_setting"] == "family"
    assert back.family in SMALL.family_sizes and back.info["heldout_fit"]  # chosen on validation; fit measured
    fit = back.info["heldout_fit"][0]
    assert -10 < fit["r2"] <= 1 and -1 <= fit["spearman"] <= 1 and fit["n_candidates"] > 0
    with pytest.raises(ValueError, match="not a GEN-LAL policy"):
        np.savez(tmp_path / "bad.npz", info=np.array(json.dumps({"format": "other"})))
        Policy.load(tmp_path / "bad.npz")


def test_the_cnn_policy_scores_candidates_on_another_mesh_only_once_adapted_to_it(tiny, cfg, tmp_path):
    cnn = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, CNN, cfg, tmp_path, log=lambda m: None)
    skin = SyntheticSpec(tuple([0.0] * 4), tuple([1.0] * 4), grid=11).build()
    x = np.random.default_rng(1).random((12, 4))
    y = np.stack([skin.solve(p, None).surface - skin.base_surface() for p in x])
    state = learner.fit(x[:6], y[:6], cfg)
    with pytest.raises(ValueError, match="vertices"):
        cnn.scores(state, x[:6], y[:6], x[6:], cfg)
    chosen = cnn.for_mesh(skin.base_surface(), cnn.scale).select(state, x[:6], y[:6], x[6:], 3, cfg)
    assert len(set(chosen.tolist())) == 3 and chosen.max() < 6


def test_a_batch_label_policy_on_a_clustered_pool_picks_a_family_member_by_its_learned_score(tiny, cfg, tmp_path):
    """Labels from clustered simulated pools; selection scores every family member and takes the best."""
    clustered = np.arange(len(tiny.policy)) % 3 != 0  # two thirds clustered candidates, the rest pseudo-test
    pol = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, PolicySettings(**{**SMALL.__dict__,
                       "family_sizes": (4,)}), cfg, tmp_path, log=lambda m: None, clustered=clustered)
    rows = np.load(tmp_path / "run_000.npz")
    assert rows["feats"].shape[1] == N_BATCH_FEATURES and len(np.unique(rows["n_labelled"])) >= 1
    for n in np.unique(rows["n_labelled"]):  # ranked within each step: centred, spanning [-0.5, 0.5]
        t = rows["target"][rows["n_labelled"] == n]
        assert abs(t.mean()) < 1e-9 and t.min() >= -0.5 and t.max() <= 0.5
    lab = np.arange(8)
    state = learner.fit(tiny.pool.x[lab], tiny.pool.y[lab], cfg)
    xl, xc = tiny.pool.x[lab], tiny.pool.x[8:]
    chosen = pol.select(state, xl, tiny.pool.y[lab], xc, 5, cfg)
    members = committee(state, xl, tiny.pool.y[lab], cfg, 2)
    ranked = state_features(members, xl, xc)
    fam = batch_family(ranked[:, :-1], xl, xc, 5, 4, family_seed(len(xl), 0x5E1))
    assert any(np.array_equal(chosen, b) for b in fam)


def test_the_candidate_label_policy_still_learns_and_selects(tiny, cfg, tmp_path):
    pol = learn_policy(tiny.policy.x, tiny.policy.y, tiny.base, CANDIDATE, cfg, tmp_path, log=lambda m: None)
    assert pol.label_mode == "candidate" and pol.diversity in CANDIDATE.diversity
    state = learner.fit(tiny.pool.x[:8], tiny.pool.y[:8], cfg)
    chosen = pol.select(state, tiny.pool.x[:8], tiny.pool.y[:8], tiny.pool.x[8:], 4, cfg)
    assert len(set(chosen.tolist())) == 4


def test_diverse_batch_spreads_out_where_top_k_piles_up():
    x_lab = np.zeros((1, 2))
    x_cand = np.array([[1.0, 1.0], [1.0, 0.99], [0.99, 1.0], [0.0, 1.0], [1.0, 0.0]])
    scores = np.array([5.0, 4.9, 4.8, 1.0, 0.9])  # the three best candidates are nearly the same pose
    assert sorted(diverse_batch(scores, x_lab, x_cand, 3, 0.0).tolist()) == [0, 1, 2]
    spread = diverse_batch(scores, x_lab, x_cand, 3, 2.0)
    assert spread[0] == 0 and set(spread[1:].tolist()) == {3, 4}


@pytest.mark.parametrize("select", ["genlal", "random"])
def test_selection_in_the_loop_grows_a_dataset_batch_by_batch_and_resumes(tmp_path, cfg, select):
    head = load_head(ROOT / "heads" / "sample" / "head.toml")
    lo, hi = sample_ranges(head)
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8)
    samples = sample_poses(head, 40, seed=3)
    policy = None
    if select == "genlal":
        skin = spec.build()
        x = np.random.default_rng(2).random((30, len(lo)))
        y = np.stack([skin.solve(lo + p * (hi - lo), None).surface - skin.base_surface() for p in x])
        policy = learn_policy(x, y, skin.base_surface(), SMALL, cfg, tmp_path / "policy", log=lambda m: None)
    kw = dict(select=select, batch=4, init=4, policy=policy, head=head.name, names=head.actuator_names,
              units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(), seed=3, sampling={},
              config=cfg, progress_stream=None, log=lambda m: None, rest_pose=head.neutral_pose)
    root = tmp_path / "ds"
    first = grow_dataset(root, spec, samples, budget=12, **kw)
    assert first["simulated"] == 12 and first["batches"] == 3 and first["retrained_this_run"] == 2
    batches = json.loads((root / "selection.json").read_text())["batches"]
    assert [len(b) for b in batches] == [4, 4, 4] and len({i for b in batches for i in b}) == 12
    other = "random" if select == "genlal" else "genlal"
    if other == "random":  # the same pool, the same initial batch: the policy chooses other poses than random
        theirs = grow_dataset(tmp_path / "ds-random", spec, samples, budget=12, **{**kw, "select": "random"})
        assert theirs["simulated"] == 12
        rand = json.loads((tmp_path / "ds-random" / "selection.json").read_text())["batches"]
        assert rand[0] == batches[0] and set(rand[1] + rand[2]) != set(batches[1] + batches[2])
    more = grow_dataset(root, spec, samples, budget=20, **kw)  # rerun with a larger budget: grows the same dataset
    assert more["simulated"] == 20 and more["retrained_this_run"] == 2
    again = json.loads((root / "selection.json").read_text())["batches"]
    assert again[:3] == batches
    ds = PoseDataset(root)
    assert len(ds.usable) == 20 and set(ds.usable.tolist()) == {i for b in again for i in b}
    np.testing.assert_array_equal(ds.rest_pose, head.neutral_pose)  # training anchors a grown dataset too


@pytest.mark.parametrize("extra, message", [
    (["--select", "genlal", "--budget", "5"], "needs --policy"),
    (["--select", "random"], "needs --budget"),
    (["--budget", "5"], "need --select"),
])
def test_the_dataset_command_names_what_is_missing_for_selection(tmp_path, capsys, extra, message):
    from likeness.cli import main

    code = main(["offline", "dataset", "--config", str(ROOT / "heads" / "sample" / "head.toml"), "--synthetic",
                 "--poses", "20", "--out", str(tmp_path / "ds"), "--engine", "serial", *extra])
    assert code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "ds").exists()
