"""KSNN training: ONNX matches PyTorch, splits stay apart, the report is reproduced by `evaluate`, resume works."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.headspec import load_head  # noqa: E402
from models.predictor import SkinPredictor  # noqa: E402
from offline.dataset.generate import generate_dataset  # noqa: E402
from offline.dataset.sampling import sample_poses  # noqa: E402
from offline.dataset.store import PoseDataset  # noqa: E402
from offline.dataset.synthetic import SyntheticSpec  # noqa: E402
from offline.engine import SerialEngine  # noqa: E402
from offline.train.ksnn import TrainConfig, hidden_candidates, resolve_hidden, torch_offsets, train_ksnn  # noqa: E402
from offline.train.pipeline import train_pipeline  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    head = load_head(ROOT / "heads" / "sample" / "head.toml")
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    root = tmp_path_factory.mktemp("ds")
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8)
    generate_dataset(root, spec, sample_poses(head, 150, seed=0), head=head.name, names=head.actuator_names,
                     units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(), seed=0, sampling={},
                     progress_stream=None)
    return root, head


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    root, _ = dataset
    out = tmp_path_factory.mktemp("out")
    cfg = TrainConfig(epochs=40, batch_size=32, lr=5e-3, patience=40)
    report = train_pipeline(root, out, cfg, hidden=["A", 26], int8=True, log=lambda s: None)
    return out, report, cfg


def test_hidden_sizes():
    assert hidden_candidates(13) == [13, 20, 26]
    assert resolve_hidden(["A"], 13) == [13]
    assert resolve_hidden(["A", "1.5A", 40], 13) == [13, 20, 40]
    assert resolve_hidden(None, 13) == [13, 20, 26]
    with pytest.raises(ValueError, match="hidden size 'B'"):
        resolve_hidden(["B"], 13)


def test_pipeline_exports_onnx_matching_torch(dataset, trained):
    root, head = dataset
    out, report, _ = trained
    sp = SkinPredictor(out / "predictor.onnx")
    sp.check_against(head)
    assert sp.hidden == report["training"]["selected_hidden"] and sp.hidden in (13, 26)
    ds = PoseDataset(root)
    P = ds.actuators[:20]
    ref = torch_offsets(sp.weights, P)
    np.testing.assert_allclose(sp.predict_offsets(P), ref, atol=1e-6 * max(1e-3, np.abs(ref).max()))
    np.testing.assert_allclose(sp.predict(P[0]), ref[0] + ds.base_vertices, atol=1e-6)
    # The int8 variant: MatMulNBits output layers, weights readable for the Jacobian.
    q = SkinPredictor(report["int8"]["predictor"])
    q.check_against(head)
    step = np.abs(sp.weights.W2).max(axis=(0, 1)) / 127  # per-column bound on the 8-bit step
    assert np.all(np.abs(q.weights.W2 - sp.weights.W2) <= step[None, None, :] + 1e-12)
    np.testing.assert_allclose(q.jacobian(P[1]), sp.jacobian(P[1]), atol=0.02 * np.abs(sp.jacobian(P[1])).max())


def test_report_test_metrics_are_what_the_model_does_on_the_test_split(dataset, trained):
    root, _ = dataset
    out, report, _ = trained
    ds = PoseDataset(root)
    sp = SkinPredictor(out / "predictor.onnx")
    test = ds.splits.test[np.isin(ds.splits.test, ds.usable)]
    assert report["splits"]["converged"]["test"] == len(test) > 0
    d = sp.predict_offsets(ds.actuators[test]).astype(np.float64) - np.asarray(ds.offsets[test], dtype=np.float64)
    err = np.sqrt((d ** 2).sum(-1))
    t = report["test"]
    assert t["mean_euclidean_um"] == pytest.approx(err.mean() * 1e6, rel=1e-6)
    assert t["rms_euclidean_um"] == pytest.approx(np.sqrt((err ** 2).mean()) * 1e6, rel=1e-6)
    assert t["p99_euclidean_um"] == pytest.approx(np.percentile(err, 99) * 1e6, rel=1e-6)
    assert t["max_euclidean_um"] == pytest.approx(err.max() * 1e6, rel=1e-6)
    rmse = np.sqrt((d ** 2).mean(axis=(0, 1))) * 1e6
    assert [t["rmse_per_coordinate_um"][k] for k in "xyz"] == pytest.approx(rmse, rel=1e-6)
    k, v = np.unravel_index(np.argmax(err), err.shape)
    assert t["max_at"]["pose_index"] == test[k] and t["max_at"]["vertex"] == v
    assert t["max_at"]["region"] == ds.region_names[ds.vertex_region[v]]
    # Per region: the synthetic sheet names each vertex after the bump that moves it most.
    assert sum(r["n_vertices"] for r in t["per_region"].values()) == ds.offsets.shape[1]
    name = t["max_at"]["region"]
    assert t["per_region"][name]["max_euclidean_um"] == pytest.approx(t["max_euclidean_um"])
    # Surface strain: principal strains of the prediction against the FEM's, per triangle (the strain guard's input).
    pos_pred = sp.predict_offsets(ds.actuators[test]).astype(np.float64) + ds.base_vertices
    pos_fem = np.asarray(ds.offsets[test], dtype=np.float64) + ds.base_vertices
    diff = np.abs(sp.principal_stretches(pos_pred) - sp.principal_stretches(pos_fem)).max(axis=-1)
    st = t["surface_strain"]
    assert st["n_triangles"] == len(ds.faces) and st["degenerate_triangles"] == 0
    assert st["p99_abs"] == pytest.approx(np.percentile(diff, 99), rel=1e-5)
    assert st["max_abs"] == pytest.approx(diff.max(), rel=1e-5) and st["max_abs"] > 0
    k, tri = np.unravel_index(np.argmax(diff), diff.shape)
    assert st["max_at"]["pose_index"] == test[k] and st["max_at"]["triangle"] == tri
    # ...and the network learned something: far better than predicting the mean training pose.
    mean_pose = np.asarray(ds.offsets[ds.split("train")]).mean(axis=0)
    baseline = np.sqrt(((mean_pose - ds.offsets[test]) ** 2).sum(-1)).mean() * 1e6
    assert t["mean_euclidean_um"] < 0.5 * baseline
    # The report is written whole, names the dataset by its content and records how it was made.
    on_disk = json.loads((out / "predictor_report.json").read_text())
    assert on_disk["dataset"]["hash"] == ds.content_hash() and on_disk["dataset"]["id"] == ds.id
    assert on_disk["mesh"]["n_surface_vertices"] == 64 and on_disk["mesh"]["element_order"] is None
    assert on_disk["splits"]["poses"] == {"train": 106, "validation": 22, "test": 22}
    assert on_disk["training"]["config"]["epochs"] == 40 and on_disk["material"]["model"] is None
    for name in ("vertex_error.png", "training_curves.png"):
        assert (out / name).stat().st_size > 1000
    assert json.loads(sp.metadata["likeness.training"])["test"]["mean_euclidean_um"] == pytest.approx(
        t["mean_euclidean_um"])


def test_hidden_size_is_chosen_on_validation_and_compared_with_h_equals_a(trained):
    _, report, _ = trained
    per = report["training"]["per_hidden"]
    assert set(per) == {"13", "26"}
    chosen = min(per, key=lambda h: per[h]["best_val_objective"])
    assert report["training"]["selected_hidden"] == int(chosen)
    cmp = report["hidden_comparison"]
    assert cmp["h_equals_a"]["hidden"] == 13 and cmp["selected"]["hidden"] == int(chosen)
    assert cmp["selected"]["test"]["mean_euclidean_um"] == pytest.approx(report["test"]["mean_euclidean_um"])
    assert cmp["h_equals_a"]["test"]["mean_euclidean_um"] > 0


def test_test_split_cannot_influence_training(dataset, tmp_path):
    """Scramble the test poses' targets: the trained weights stay bit-identical (only the test metrics move)."""
    root, _ = dataset
    copy = tmp_path / "scrambled"
    shutil.copytree(root, copy)
    ds = PoseDataset(copy)
    test = ds.splits.test
    off = np.load(copy / "offsets.npy", mmap_mode="r+")
    off[test] = off[test] * 3.0 + 0.001
    off.flush()
    del off
    cfg = TrainConfig(epochs=8, batch_size=32, patience=100)
    a = train_pipeline(root, tmp_path / "a", cfg, hidden=["A"], log=lambda s: None)
    b = train_pipeline(copy, tmp_path / "b", cfg, hidden=["A"], log=lambda s: None)
    wa = SkinPredictor(tmp_path / "a" / "predictor.onnx").weights
    wb = SkinPredictor(tmp_path / "b" / "predictor.onnx").weights
    for name in ("W1", "b1", "W2", "b2"):
        np.testing.assert_array_equal(getattr(wa, name), getattr(wb, name))
    for doc in (a, b):
        doc["training"]["per_hidden"]["13"].pop("train_seconds")
    assert a["training"]["per_hidden"] == b["training"]["per_hidden"]
    assert b["test"]["mean_euclidean_um"] > 2 * a["test"]["mean_euclidean_um"]
    assert a["dataset"]["hash"] != b["dataset"]["hash"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "likeness", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=120)


def test_evaluate_cli_reproduces_the_report_and_catches_a_tampered_one(dataset, trained, tmp_path):
    root, _ = dataset
    out, report, _ = trained
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root))
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["matches"] and doc["differences"] == []
    assert doc["test"]["max_euclidean_um"] == pytest.approx(report["test"]["max_euclidean_um"], rel=1e-9)
    bad = json.loads((out / "predictor_report.json").read_text())
    bad["test"]["per_region"]["bump_0"]["mean_euclidean_um"] *= 0.9
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root),
               "--report", str(tmp_path / "bad.json"))
    assert res.returncode == 1
    assert any("per_region.bump_0.mean_euclidean_um" in d for d in json.loads(res.stdout)["differences"])
    # A report from before the splits (no format, no test block) is refused with a clear message.
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"held_out": {"rmse_um": 1.0}}))
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root),
               "--report", str(old))
    assert res.returncode == 2 and not res.stdout and "not a predictor report with test metrics" in res.stderr
    # --split all: every converged pose (for datasets of fresh poses the predictor never saw); no report check.
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root),
               "--split", "all")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["all"]["n_poses"] == len(PoseDataset(root).usable)
    # --worst N: the N poses with the largest vertex error, worst first; the first is where the split's max sits.
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root),
               "--split", "test", "--report", str(tmp_path / "none.json"), "--worst", "3")
    assert res.returncode == 2 and "--worst" in res.stderr  # a report check lists no poses
    res = _cli("offline", "evaluate", "--predictor", str(out / "predictor.onnx"), "--dataset", str(root),
               "--split", "validation", "--worst", "3")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    worst = doc["worst_poses"]
    assert len(worst) == 3 and [w["max_euclidean_um"] for w in worst] == sorted(
        (w["max_euclidean_um"] for w in worst), reverse=True)
    assert worst[0]["max_euclidean_um"] == pytest.approx(doc["validation"]["max_euclidean_um"], rel=1e-9)
    assert (worst[0]["pose_index"], worst[0]["vertex"]) == (doc["validation"]["max_at"]["pose_index"],
                                                           doc["validation"]["max_at"]["vertex"])
    ds = PoseDataset(root)
    assert {w["pose_index"] for w in worst} <= set(ds.split("validation").tolist())


def test_training_resumes_from_checkpoint(dataset, tmp_path):
    root, _ = dataset
    ds = PoseDataset(root)
    x = (ds.actuators - ds.lo) / (ds.hi - ds.lo)
    tr, va = ds.split("train"), ds.split("validation")
    ck = tmp_path / "ck.pt"
    msgs: list[str] = []
    first = train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi,
                       TrainConfig(epochs=6, patience=100), checkpoint=ck, log=msgs.append)
    assert len(first.history["val"]) == 6 and ck.exists()
    second = train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi,
                        TrainConfig(epochs=10, patience=100), checkpoint=ck, log=msgs.append)
    assert any("resumed at epoch 6" in m for m in msgs)
    assert len(second.history["val"]) == 10
    assert second.history["val"][:6] == first.history["val"]
    assert second.best_val_mse <= first.best_val_mse
    # Same sizes, other poses: the checkpoint belongs to another split and is not resumed.
    msgs.clear()
    swapped_tr = np.sort(np.concatenate([tr[1:], va[:1]]))
    swapped_va = np.sort(np.concatenate([va[1:], tr[:1]]))
    third = train_ksnn(x, ds.offsets, swapped_tr, swapped_va, 13, ds.lo, ds.hi,
                       TrainConfig(epochs=3, patience=100), checkpoint=ck, log=msgs.append)
    assert not any("resumed" in m for m in msgs) and len(third.history["val"]) == 3


def test_rest_anchor_pins_the_exported_predictor_to_zero_at_the_rest_pose(dataset, trained, tmp_path):
    """A dataset that records its rest pose (zero offsets by construction) gets a predictor that is exactly zero
    there; a dataset written before rest poses were recorded gains it on resume; without one nothing is pinned."""
    from scipy.optimize import brentq

    _root, head = dataset
    assert trained[1]["training"]["rest_anchor"]["anchored"] is False  # the fixture's dataset records no rest pose
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8)
    prob = spec.build()
    x0 = brentq(lambda x: np.sin(1.4 * (x - 0.3)) + 0.3 * x * x, 0, 0.3)  # the sheet's forcing law, per actuator
    rest = lo + x0 * (hi - lo)
    assert np.abs(prob.forcing(rest)).max() < 1e-12  # the sheet is at rest there
    ds_root = tmp_path / "ds"
    kw = dict(head=head.name, names=head.actuator_names, units=["rad"] * len(lo), lo=lo, hi=hi,
              engine=SerialEngine(), seed=0, sampling={}, progress_stream=None)
    generate_dataset(ds_root, spec, sample_poses(head, 60, seed=1), max_poses=30, **kw)
    assert PoseDataset(ds_root).rest_pose is None
    generate_dataset(ds_root, spec, sample_poses(head, 60, seed=1), rest_pose=rest, **kw)  # resume, backfill
    ds = PoseDataset(ds_root)
    np.testing.assert_array_equal(ds.rest_pose, rest)
    with pytest.raises(ValueError, match="rest_pose"):
        generate_dataset(tmp_path / "bad", spec, sample_poses(head, 10, seed=1), rest_pose=rest[:3], **kw)
    cfg = TrainConfig(epochs=30, batch_size=16, lr=5e-3, patience=30)
    report = train_pipeline(ds_root, tmp_path / "out", cfg, hidden=["A"], log=lambda s: None)
    assert report["training"]["rest_anchor"]["anchored"] is True
    sp = SkinPredictor(tmp_path / "out" / "predictor.onnx")
    scale = np.abs(sp.predict_offsets(ds.actuators[:20])).max()
    assert scale > 0
    assert np.abs(sp.predict_offsets(rest[None])).max() < 1e-5 * scale  # float32 graph: rounding only
    assert np.abs(sp.weights.offsets(rest)).max() < 1e-6 * scale  # float32 weights, float64 arithmetic
    free = train_pipeline(ds_root, tmp_path / "free", TrainConfig(epochs=30, batch_size=16, lr=5e-3, patience=30,
                                                                 rest_anchor=False), hidden=["A"], log=lambda s: None)
    assert free["training"]["rest_anchor"]["anchored"] is False
    unpinned = SkinPredictor(tmp_path / "free" / "predictor.onnx")
    assert np.abs(unpinned.predict_offsets(rest[None])).max() > 1e-3 * scale


def test_surface_edges_are_unique_with_their_rest_lengths():
    from offline.train.pipeline import surface_edges

    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [1, 2, 0]])
    edges, length = surface_edges(v, np.array([[0, 1, 2], [1, 3, 2]]))
    assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    np.testing.assert_allclose(length, [1, 2, np.sqrt(5), 2, 1])
    with pytest.raises(ValueError, match="zero length"):
        surface_edges(np.zeros((3, 3)), np.array([[0, 1, 2]]))


def test_the_edge_strain_term_weighs_each_edge_error_over_its_rest_length_and_keeps_its_own_checkpoints(
        dataset, tmp_path):
    from offline.train.ksnn import make_objective

    edges = (np.array([[0, 1], [1, 2]]), np.array([0.5, 2.0]))
    scale = np.array([2.0, 1.0, 1.0])
    pred = torch.zeros(3, 1, 3)
    target = torch.zeros(3, 1, 3)
    pred[0, 0, 1] = 0.01  # x offset of vertex 1 off by 0.01 scaled = 0.02 m
    plain = float(make_objective(scale, None, 0.0)(pred, target))
    edged = float(make_objective(scale, edges, 3.0)(pred, target))
    assert plain == pytest.approx(0.01 ** 2 / 9)
    # Edge strain errors: 0.02 / 0.5 and 0.02 / 2.0 on the x axis, zero elsewhere; mean over 3 axes x 2 edges.
    assert edged - plain == pytest.approx(3.0 * ((0.02 / 0.5) ** 2 + (0.02 / 2.0) ** 2) / 6, rel=1e-5)
    root, _ = dataset
    cfg = TrainConfig(epochs=6, batch_size=32, patience=30)
    a = train_pipeline(root, tmp_path / "out", cfg, hidden=["A"], log=lambda s: None)
    logs: list[str] = []
    b = train_pipeline(root, tmp_path / "out", TrainConfig(epochs=6, batch_size=32, patience=30, edge_weight=10.0),
                       hidden=["A"], log=logs.append)  # the same folder: the offsets-only checkpoint is not resumed
    assert not any("resumed" in line for line in logs)
    assert b["training"]["config"]["edge_weight"] == 10.0
    assert "surface_strain" in b["training"]["per_hidden"]["13"]["validation"]
    assert a["test"]["mean_euclidean_um"] != b["test"]["mean_euclidean_um"]  # the term changed what was learned


def test_a_larger_error_power_weighs_a_pose_s_worst_vertex_more_and_keeps_its_own_checkpoints(dataset, tmp_path):
    from offline.train.ksnn import make_objective

    scale = np.ones(3)
    target = torch.zeros(3, 2, 4)
    spread = torch.full((3, 2, 4), 0.1)  # every vertex off by 0.1 on every axis
    peaked = torch.zeros(3, 2, 4)
    peaked[:, 0, 0] = 0.1 * np.sqrt(8)  # the same squared error, all on one vertex of one pose
    mse, l8 = make_objective(scale, None, 0.0), make_objective(scale, None, 0.0, error_power=8.0)
    assert float(mse(spread, target)) == pytest.approx(float(mse(peaked, target)))
    assert float(l8(spread, target)) == pytest.approx(0.01, rel=1e-5)  # spread evenly: the power mean is the MSE
    # all on one of 8 vertices: mean of (8 * 0.01)^4 over 8, to the 1/4 = 0.08 / 8^(1/4)
    assert float(l8(peaked, target)) == pytest.approx(0.08 / 8 ** 0.25, rel=1e-5)
    with pytest.raises(ValueError, match="error_power must be at least 2"):
        make_objective(scale, None, 0.0, error_power=1.0)
    root, _ = dataset
    logs: list[str] = []
    train_pipeline(root, tmp_path / "out", TrainConfig(epochs=4, batch_size=32, patience=30), hidden=["A"],
                   log=lambda s: None)
    b = train_pipeline(root, tmp_path / "out", TrainConfig(epochs=4, batch_size=32, patience=30, error_power=6.0),
                       hidden=["A"], log=logs.append)  # the MSE run's checkpoint is not resumed
    assert not any("resumed" in line for line in logs)
    assert b["training"]["config"]["error_power"] == 6.0


def test_an_output_rank_trains_a_wide_hidden_layer_whose_solve_runs_in_that_rank(dataset, tmp_path):
    """``output_rank`` r: each axis' output layer is trained as C U (H × r, r × V) and exported as their product, an
    ordinary predictor file whose W2 has rank r; the in-cycle solve reads the rank off it (a residual of r rows per
    axis) and its frame solve from channel values is the fused solve, as at full rank."""
    from models.ksnn_solve import KsnnInverse
    from models.strain_guard import StrainGuard
    from offline.train.ksnn import output_rank

    assert output_rank("2A", 13) == 26 and output_rank(0, 13) == 0 and output_rank("0", 13) == 0
    with pytest.raises(ValueError, match="output rank 'x'"):
        output_rank("x", 13)
    root, _ = dataset
    logs: list[str] = []
    report = train_pipeline(root, tmp_path / "out", TrainConfig(epochs=20, batch_size=32, patience=30, output_rank="A"),
                            hidden=["3A"], log=logs.append)
    assert report["training"]["config"]["output_rank"] == "A"
    sp = SkinPredictor(tmp_path / "out" / "predictor.onnx")
    assert sp.hidden == 39
    for k in range(3):
        s = np.linalg.svd(sp.weights.W2[k], compute_uv=False)
        assert s[12] > 1e-3 * s[0] and s[13] < 1e-5 * s[0]  # rank 13, as stored in float32
    units = np.random.default_rng(3).normal(size=(5, sp.n_vertices, 3)) * 1e-3
    inv = KsnnInverse(sp.weights, units)
    assert inv.rank == 13 and inv._Rb.shape == (3, 13, 39)
    guard = StrainGuard(sp, 0.5 * (sp.lo + sp.hi), samples=300)
    frame = inv.frame_solve(3, 1e-6, 1e-3, guard)
    kept = inv.frame_state(frame.reuse.frames)
    rng = np.random.default_rng(4)
    p_prev = 0.5 * (sp.lo + sp.hi)
    for _ in range(10):
        values = np.where(rng.random(inv.n_units) < 0.3, rng.uniform(0.0, 1.0, inv.n_units), np.nan)
        w = np.where(np.isfinite(values), values, 0.0)
        a = inv.solve(w, p_prev=p_prev, max_iterations=3, tol=1e-6, xtol=1e-3, measure=guard, reuse=kept)
        p = frame(values, p_prev)
        np.testing.assert_array_equal(p, a.p)
        assert (frame.iterations, frame.strain) == (a.iterations, a.strain)
        p_prev = p.copy()
    # its own checkpoints: a full-rank run of the same size does not resume it
    logs.clear()
    train_pipeline(root, tmp_path / "out", TrainConfig(epochs=2, batch_size=32, patience=30), hidden=["3A"],
                   log=logs.append)
    assert not any("resumed" in line for line in logs)


def test_the_tail_hinge_charges_only_errors_past_its_threshold_and_keeps_its_own_checkpoints(dataset, tmp_path):
    from offline.train.ksnn import make_objective

    scale = np.array([1e-3, 2e-3, 2e-3])  # metres per scaled unit
    target = torch.zeros(3, 2, 4)
    small = torch.zeros(3, 2, 4)
    small[1, 0, 0] = 0.2  # 0.4 mm on one vertex: under a 0.5 mm threshold
    large = torch.zeros(3, 2, 4)
    large[1, 0, 0] = 0.5  # 1 mm: 0.5 mm past it
    mse = make_objective(scale, None, 0.0)
    tailed = make_objective(scale, None, 0.0, tail_threshold=0.5e-3, tail_weight=100.0)
    assert float(tailed(small, target)) == pytest.approx(float(mse(small, target)))
    excess = 100.0 * (0.5e-3) ** 2 / 8 / np.mean(scale ** 2)  # one of 8 (pose, vertex) pairs, in scaled units
    assert float(tailed(large, target)) == pytest.approx(float(mse(large, target)) + excess, rel=1e-4)
    with pytest.raises(ValueError, match="tail_threshold and tail_weight"):
        make_objective(scale, None, 0.0, tail_threshold=-1.0, tail_weight=1.0)
    root, _ = dataset
    logs: list[str] = []
    train_pipeline(root, tmp_path / "out", TrainConfig(epochs=4, batch_size=32, patience=30), hidden=["A"],
                   log=lambda s: None)
    b = train_pipeline(root, tmp_path / "out",
                       TrainConfig(epochs=4, batch_size=32, patience=30, tail_threshold=1e-4, tail_weight=50.0),
                       hidden=["A"], log=logs.append)  # the run without the hinge is not resumed
    assert not any("resumed" in line for line in logs)
    assert b["training"]["config"]["tail_weight"] == 50.0


def test_a_weight_decay_shrinks_the_weights_and_keeps_its_own_checkpoints(dataset, tmp_path):
    root, _ = dataset

    def first_layer_norm() -> float:
        return float(np.linalg.norm(SkinPredictor(tmp_path / "out" / "predictor.onnx").weights.W1))

    train_pipeline(root, tmp_path / "out", TrainConfig(epochs=6, batch_size=32, patience=30), hidden=["A"],
                   log=lambda s: None)
    plain = first_layer_norm()
    logs: list[str] = []
    decayed = train_pipeline(root, tmp_path / "out", TrainConfig(epochs=6, batch_size=32, patience=30,
                                                                 weight_decay=0.5), hidden=["A"], log=logs.append)
    assert not any("resumed" in line for line in logs)  # the run without decay is not resumed
    assert decayed["training"]["config"]["weight_decay"] == 0.5
    assert first_layer_norm() < plain


def test_a_run_can_start_from_an_earlier_runs_best_weights_on_the_same_poses(dataset, tmp_path):
    """``init``: a fine-tune starts from the checkpoint's best weights (its first epoch's validation objective is
    near that run's best, not a random start's), records the checkpoint by content, keeps its own checkpoints; a
    checkpoint of another network form or of other training poses is refused by name."""
    root, _ = dataset
    ds = PoseDataset(root)
    x = (ds.actuators - ds.lo) / (ds.hi - ds.lo)
    tr, va = ds.split("train"), ds.split("validation")
    ck = tmp_path / "base.pt"
    base = train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi, TrainConfig(epochs=30, patience=100), checkpoint=ck)
    fresh = train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi, TrainConfig(epochs=1, patience=100, seed=5))
    tuned = train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi,
                       TrainConfig(epochs=1, patience=100, lr=1e-4, init=str(ck)), checkpoint=tmp_path / "ft.pt")
    assert tuned.history["val"][0] < 1.5 * base.best_val_mse < fresh.history["val"][0]
    with pytest.raises(ValueError, match="hidden size and output rank"):
        train_ksnn(x, ds.offsets, tr, va, 20, ds.lo, ds.hi, TrainConfig(epochs=1, init=str(ck)))
    other_tr = tr[: len(tr) // 2]
    with pytest.raises(ValueError, match="other training poses"):
        train_ksnn(x, ds.offsets, other_tr, va, 13, ds.lo, ds.hi, TrainConfig(epochs=1, init=str(ck)))
    with pytest.raises(ValueError, match="no such file"):
        train_ksnn(x, ds.offsets, tr, va, 13, ds.lo, ds.hi, TrainConfig(epochs=1, init=str(tmp_path / "none.pt")))
    report = train_pipeline(root, tmp_path / "out", TrainConfig(epochs=2, patience=30, lr=1e-4, init=str(ck)),
                            hidden=["A"], log=lambda s: None)
    import hashlib

    assert report["training"]["init"] == {"checkpoint": str(ck), "sha256": hashlib.sha256(ck.read_bytes()).hexdigest()}
