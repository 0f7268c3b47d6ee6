"""SkinPredictor: ONNX vs reference forward pass, metadata validation by name, Jacobian, surface stretch."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from models.headspec import load_head
from models.onnx_tensors import read_initializers
from models.predictor import KsnnWeights, SkinPredictor

ROOT = Path(__file__).resolve().parents[2]
HEAD = ROOT / "heads" / "sample" / "head.toml"


def random_weights(rng, lo, hi, hidden=20, n_vertices=300) -> KsnnWeights:
    A = len(lo)
    return KsnnWeights(
        np.asarray(lo, float), np.asarray(hi, float),
        rng.normal(size=(3, A, hidden)), rng.normal(size=(3, hidden)) * 0.5,
        rng.normal(size=(3, hidden, n_vertices)) * 1e-3, rng.normal(size=(3, n_vertices)) * 1e-4,
    )


def grid_surface(n: int = 10, size: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def write_model(tmp_path: Path, head, seed: int = 0, hidden: int = 20, face_units: int = 3):
    pytest.importorskip("onnx")
    from offline.train.export import export_predictor, predictor_metadata

    rng = np.random.default_rng(seed)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    base, faces = grid_surface()
    w = random_weights(rng, lo, hi, hidden, base.shape[0])
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    fu = rng.normal(size=(face_units, base.shape[0], 3)) * 1e-3
    meta = predictor_metadata(head=head.name, names=head.actuator_names, units=units, weights=w,
                              base_vertices=base, faces=faces, face_unit_names=[f"u{i}" for i in range(face_units)],
                              face_unit_offsets=fu)
    path = export_predictor(tmp_path / "predictor.onnx", w, meta)
    return path, w, base, faces, fu


@pytest.fixture(scope="module")
def head():
    return load_head(HEAD)


def test_onnx_matches_reference_single_and_batch(tmp_path, head):
    path, w, base, _faces, fu = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    rng = np.random.default_rng(1)
    P = rng.uniform(sp.lo, sp.hi, size=(7, sp.n_actuators))
    ref = np.stack([w.offsets(p) for p in P])
    batch = sp.predict(P)
    assert batch.shape == (7, base.shape[0], 3)
    np.testing.assert_allclose(batch, ref + base, atol=2e-7)
    np.testing.assert_allclose(sp.predict(P[3]), ref[3] + base, atol=2e-7)
    np.testing.assert_allclose(sp.predict_offsets(P[3]), ref[3], atol=2e-7)
    assert sp.face_unit_names == ("u0", "u1", "u2")
    np.testing.assert_allclose(sp.face_unit_offsets, fu, rtol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        sp.predict(np.zeros(sp.n_actuators + 1))
    with pytest.raises(ValueError, match="finite"):
        sp.predict(np.full(sp.n_actuators, np.nan))


def test_initializer_reader_matches_onnx(tmp_path, head):
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    path, w, *_ = write_model(tmp_path, head)
    mine = read_initializers(path)
    ref = {t.name: numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}
    assert set(mine) == set(ref)
    for name, arr in ref.items():
        np.testing.assert_array_equal(mine[name], arr)
    sp = SkinPredictor(path)
    np.testing.assert_allclose(sp.weights.W2, w.W2, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(sp.weights.hi, w.hi, rtol=1e-6)


def test_check_against_accepts_own_head_and_refuses_mismatches_by_name(tmp_path, head):
    path, *_ = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    sp.check_against(head)
    acts = list(head.actuators)
    renamed = dataclasses.replace(head, actuators=(dataclasses.replace(acts[0], name="jaw2"), *acts[1:]))
    with pytest.raises(SpecError, match=r"model actuator\(s\) not in head 'sample': jaw$"):
        sp.check_against(renamed)
    swapped = dataclasses.replace(head, actuators=(acts[1], acts[0], *acts[2:]))
    with pytest.raises(SpecError, match="order differs at position 0: model has 'jaw'"):
        sp.check_against(swapped)
    wider = dataclasses.replace(head, actuators=(*acts[:-1], dataclasses.replace(acts[-1], max=acts[-1].max + 0.1)))
    with pytest.raises(SpecError, match=r"actuators\.lid_r\.range"):
        sp.check_against(wider)
    sp.check_against(wider, require_full_range=False)  # trained on part of the range: accepted on request...
    off_neutral = dataclasses.replace(head, actuators=(*acts[:-1], dataclasses.replace(
        acts[-1], min=acts[-1].max + 0.1, max=acts[-1].max + 0.3, neutral=acts[-1].max + 0.2)))
    with pytest.raises(SpecError, match=r"lid_r.*does not cover the head's neutral"):
        sp.check_against(off_neutral, require_full_range=False)  # ...only if it covers the neutral pose
    fewer = dataclasses.replace(head, actuators=tuple(acts[:-1]))
    with pytest.raises(SpecError, match="lid_r"):
        sp.check_against(fewer)
    linear = dataclasses.replace(head, actuators=(dataclasses.replace(acts[0], kind="linear"), *acts[1:]))
    with pytest.raises(SpecError, match=r"actuators\.jaw\.unit"):
        sp.check_against(linear)


def test_bad_files_are_refused_with_the_key(tmp_path, head):
    with pytest.raises(SpecError, match="not found"):
        SkinPredictor(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(SpecError, match="graph"):
        SkinPredictor(tmp_path / "junk.onnx")
    onnx = pytest.importorskip("onnx")
    path, *_ = write_model(tmp_path, head)
    model = onnx.load(str(path))
    for p in model.metadata_props:
        if p.key == "likeness.format_version":
            p.value = "99"
    bad = tmp_path / "v99.onnx"
    bad.write_bytes(model.SerializeToString())
    with pytest.raises(SpecError, match="format_version"):
        SkinPredictor(bad)


def test_jacobian_matches_finite_differences(tmp_path, head):
    path, w, *_ = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    rng = np.random.default_rng(2)
    p = rng.uniform(sp.lo, sp.hi)
    J = sp.jacobian(p)
    assert J.shape == (sp.n_vertices * 3, sp.n_actuators)
    eps = 1e-6
    for a in range(sp.n_actuators):
        d = np.zeros(sp.n_actuators)
        d[a] = eps
        fd = (w.offsets(p + d) - w.offsets(p - d)).reshape(-1) / (2 * eps)
        np.testing.assert_allclose(J[:, a], fd, atol=1e-7 * np.abs(J).max())


def test_principal_stretches(tmp_path, head):
    path, _w, base, faces, _ = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    s = sp.principal_stretches(base)
    np.testing.assert_allclose(s, 1.0, atol=1e-6)
    rot = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(sp.principal_stretches(base @ rot.T + 0.3), 1.0, atol=1e-6)
    stretched = base * np.array([1.3, 0.9, 1.0])
    s = sp.principal_stretches(stretched)
    np.testing.assert_allclose(s[:, 0], 0.9, atol=1e-5)
    np.testing.assert_allclose(s[:, 1], 1.3, atol=1e-5)
    assert len(sp.strain_violations(stretched)) == 0
    over = base * np.array([1.6, 1.0, 1.0])
    assert len(sp.strain_violations(over)) == len(faces)
    lo, hi = sp.strain_extremes(base * np.array([0.75, 1.0, 1.0]))
    assert lo == pytest.approx(-0.25, abs=1e-5) and hi == pytest.approx(0.0, abs=1e-5)
    assert sp.principal_stretches(np.stack([base, stretched])).shape == (2, len(faces), 2)


def test_out_buffers_give_identical_results_and_are_checked(tmp_path, head):
    path, w, base, *_ = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    rng = np.random.default_rng(4)
    P = rng.uniform(sp.lo, sp.hi, size=(5, sp.n_actuators))
    batch = sp.predict_offsets(P)
    out = np.full((sp.n_vertices, 3), np.nan, dtype=np.float32)
    for i, p in enumerate(P):  # the one-pose path reuses its bound input buffer: every pose must come through
        assert sp.predict_offsets(p, out=out) is out
        np.testing.assert_array_equal(sp.predict_offsets(p), out)  # same kernel, same bits
        np.testing.assert_allclose(out, batch[i], rtol=1e-5, atol=1e-9)  # one row vs a batch: rounding only
    first = sp.predict_offsets(P[0])
    first_copy = first.copy()
    sp.predict_offsets(P[1])
    np.testing.assert_array_equal(first, first_copy)  # a returned array is never overwritten by a later call
    outb = np.empty((5, sp.n_vertices, 3), dtype=np.float32)
    assert sp.predict(P, out=outb) is outb
    np.testing.assert_allclose(outb, np.stack([w.offsets(p) for p in P]) + base, atol=2e-7)
    np.testing.assert_allclose(sp.predict(P[2], out=out), outb[2], rtol=1e-5, atol=1e-9)
    for bad in (np.empty((sp.n_vertices, 3), dtype=np.float64), np.empty((sp.n_vertices + 1, 3), dtype=np.float32),
                np.empty((3, sp.n_vertices), dtype=np.float32).T, np.empty((5, sp.n_vertices, 3), dtype=np.float32)):
        with pytest.raises(ValueError, match="out must be"):
            sp.predict_offsets(P[0], out=bad)


def test_int8_variant_stays_close_to_float(tmp_path, head):
    pytest.importorskip("onnx")
    from offline.train.export import export_int8

    path, w, *_ = write_model(tmp_path, head)
    sp = SkinPredictor(path)
    q = SkinPredictor(export_int8(path, tmp_path / "int8.onnx"))
    rng = np.random.default_rng(5)
    P = rng.uniform(sp.lo, sp.hi, size=(32, sp.n_actuators))
    ref = sp.predict_offsets(P)
    got = q.predict_offsets(P)
    scale = float(np.sqrt(np.mean(ref ** 2)))
    rms = float(np.sqrt(np.mean((got - ref) ** 2)))
    assert 0 < rms < 0.02 * scale  # quantized (not a float copy), yet within 2 % of the offsets' RMS
    out = np.empty((sp.n_vertices, 3), dtype=np.float32)
    np.testing.assert_allclose(q.predict_offsets(P[3], out=out), got[3], rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(q.weights.W2, w.W2, atol=0.01 * np.abs(w.W2).max())  # dequantized weights


def test_shipped_sample_predictor_loads_and_matches_its_weights():
    sp = SkinPredictor(ROOT / "heads" / "sample" / "predictor.onnx")
    p = (sp.lo + sp.hi) / 2
    np.testing.assert_allclose(sp.predict_offsets(p), sp.weights.offsets(p), atol=1e-6)
