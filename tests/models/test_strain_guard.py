"""The skin-strain guard: the measure on known deformations, the reduced check vs the full one, the FEM sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from models.kernel_support import kernels_available
from models.strain_guard import StrainGuard, SurfaceStrain, load_footprint

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"
FEM_SAMPLE = Path(__file__).resolve().parent / "data" / "strain_guard_fem_sample.npz"


def grid(n=16, size=0.06, z=0.0):
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_measure_reads_rigid_motion_as_zero_and_a_uniform_stretch_exactly():
    verts, faces = grid()
    s = SurfaceStrain(verts, faces, radius=0.008, band=0.0)
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    lo, hi = s.extremes(verts @ rot.T + [0.01, 0.02, 0.03])
    assert abs(lo) < 1e-7 and abs(hi) < 1e-7  # sqrt of a near-zero discriminant: ~1e-8
    stretched = verts * [1.3, 0.9, 1.0]
    lo, hi = s.extremes(stretched)
    assert lo == pytest.approx(-0.1, abs=1e-12) and hi == pytest.approx(0.3, abs=1e-12)


def test_band_leaves_out_the_rim_of_an_attachment_and_smoothing_caps_a_single_triangle():
    verts, faces = grid()
    # A rigid attachment along the edge x < 8 mm: distance of each triangle's centroid to it.
    rim = np.maximum(verts[faces].mean(axis=1)[:, 0] - 0.008, 0.0)
    s = SurfaceStrain(verts, faces, rim, radius=0.008, band=0.005)
    near = rim < 0.005
    assert near.any() and not s.kept[near].any() and s.kept[~near].all()
    # One vertex pushed out of plane strains its six triangles hard; the neighbourhood average stays far lower.
    bump = verts.copy()
    centre = 8 * 16 + 8
    bump[centre, 2] += 0.004
    single = s.triangle_strains(bump)[:, 1].max()
    assert single > 0.3 and s.extremes(bump)[1] < 0.5 * single
    # A bump inside the band (all its triangles' centroids within 6.7 mm of the attachment) does not count.
    wide = SurfaceStrain(verts, faces, rim, radius=0.008, band=0.007)
    bumped = verts.copy()
    bumped[3 * 16 + 8, 2] += 0.004
    assert wide.extremes(bumped)[1] < 1e-9 < wide.triangle_strains(bumped)[:, 1].max()


def test_neighbourhoods_do_not_reach_across_a_gap():
    a, fa = grid(8, 0.03)
    b, fb = grid(8, 0.03, z=0.002)  # a second sheet 2 mm away, not connected (like the lips)
    verts = np.vstack([a, b])
    faces = np.vstack([fa, fb + len(a)])
    s = SurfaceStrain(verts, faces, radius=0.008, band=0.0)
    S = s.smooth.tocoo()
    first = len(fa)
    assert not np.any((S.row < first) & (S.col >= first)) and not np.any((S.row >= first) & (S.col < first))


@pytest.fixture(scope="module")
def guard():
    g = StrainGuard.for_head(load_head(SAMPLE))
    assert g is not None
    return g


def test_reduced_check_agrees_with_the_full_measure_on_fresh_poses(guard):
    rng = np.random.default_rng(12345)  # not the calibration seed
    P = rng.uniform(guard.lo, guard.hi, (1500, len(guard.lo)))
    edge = rng.random(P.shape) < 0.1
    P[edge] = np.where(rng.random(edge.sum()) < 0.5, guard.lo[np.nonzero(edge)[1]], guard.hi[np.nonzero(edge)[1]])
    full = guard.full_batch(P)
    lo, hi = guard.strain_range
    full_ok = (full[:, 0] >= lo) & (full[:, 1] <= hi)
    reduced_ok = np.array([guard.check(p) for p in P])
    assert full_ok.any() and (~full_ok).any()
    assert np.mean(full_ok == reduced_ok) >= 0.999
    # The reduced measure is the full one over a subset of patches: never beyond it.
    red = np.array([guard.measure(p) for p in P[:200]])
    assert np.all(red[:, 1] <= full[:200, 1] + 1e-5) and np.all(red[:, 0] >= full[:200, 0] - 1e-5)


def test_edges_through_the_output_layers_basis_are_the_edges(guard):
    """``edge_basis``: the measured vertices' offsets depend on the hidden layer through the output layer's
    directions (fewer than the hidden units for a network trained with ``--output-rank``), so (Q h) F gives h E; the
    measure through the basis is the plain one within float32 rounding, compiled and in numpy, and a basis that
    would save too little is not used. The sample network's maps are given two thirds of its width's rank by a
    projection of each axis' hidden space, so the check does not depend on the shipped network's form."""
    import copy

    from models.strain_guard import edge_basis

    Q0, E = guard.kernel_arrays()[:2]
    if Q0.shape[1]:  # the head's guard uses a basis: the plain maps are its product
        E = np.matmul(Q0.transpose(0, 2, 1), E)
    E = np.array(E, dtype=np.float64)  # a copy: the guard's own maps stay as they are
    H = E.shape[1]
    rank = 2 * H // 3
    rng = np.random.default_rng(9)
    for k in range(3):  # E_k's rows through a rank-`rank` projection of the hidden space
        U = np.linalg.qr(rng.standard_normal((H, rank)))[0]
        E[k] = U @ (U.T @ E[k])
    Q, F = edge_basis(E, worth=1.0)
    assert Q.shape == (3, rank, H) and F.shape == (3, rank, E.shape[2])
    assert edge_basis(E, worth=0.5)[0].shape == (3, 0, H)  # two thirds: too little saved
    plain, based = copy.copy(guard), copy.copy(guard)
    plain._Q, plain._E = np.zeros((3, 0, H), np.float32), np.ascontiguousarray(E, dtype=np.float32)
    based._Q, based._E = Q, F
    for p in rng.uniform(guard.lo, guard.hi, (200, len(guard.lo))):
        h = guard.hidden(p)
        np.testing.assert_allclose(based.measure_hidden(h), plain.measure_hidden(h), rtol=0, atol=1e-5)
        np.testing.assert_allclose(based.measure_hidden_numpy(h), plain.measure_hidden_numpy(h), rtol=0, atol=1e-5)


def test_the_compiled_reduced_measure_matches_numpy(guard):
    """The in-cycle measure, compiled (its metric in float64) against the numpy one (float32 metric)."""
    rng = np.random.default_rng(7)
    for p in rng.uniform(guard.lo, guard.hi, (300, len(guard.lo))):
        h = guard.hidden(p)
        fast = guard.measure_hidden(h)
        ref = guard.measure_hidden_numpy(h)
        np.testing.assert_allclose(fast, ref, rtol=0, atol=5e-5)


def test_full_pass_matches_the_onnx_predictor_and_neutral_reads_near_zero(guard):
    n = guard.neutral
    assert guard.check(n)
    lo, hi = guard.full(n)  # ONNX pass (float32)
    ref = guard.full_batch(n[None])[0]  # numpy pass
    assert lo == pytest.approx(ref[0], abs=1e-4) and hi == pytest.approx(ref[1], abs=1e-4)
    assert -0.1 < lo <= 0.0 <= hi < 0.1  # the rest reference: the predictor's neutral error stays small


def test_out_of_range_and_non_finite_poses_are_refused(guard):
    p = guard.neutral.copy()
    p[0] = guard.hi[0] + 0.05
    assert not guard.check(p)
    p[0] = np.nan
    assert not guard.check(p)
    with pytest.raises(ValueError, match="shape"):
        guard.check(np.zeros(3))


def test_limit_returns_ok_limited_or_held(guard):
    rng = np.random.default_rng(3)
    P = rng.uniform(guard.lo, guard.hi, (200, len(guard.lo)))
    bad = next(p for p in P if not guard.check(p))
    n = guard.neutral
    pose, outcome = guard.limit(n, n)
    assert outcome == "ok" and np.array_equal(pose, n)
    pose, outcome = guard.limit(n, bad, steps=6)
    assert outcome in ("limited", "held")
    assert guard.check(pose)
    if outcome == "limited":
        assert 0 < np.linalg.norm(pose - n) < np.linalg.norm(bad - n)


@pytest.mark.skipif(not kernels_available(), reason="numba is not installed")
def test_the_compiled_limit_is_the_bisection_over_the_check(guard):
    """One compiled call (models._skin_kernels.guard_limit) against the bisection over the check, on segments from
    neutral and between random poses, in and beyond the trained range (NaN targets held)."""
    rng = np.random.default_rng(11)
    span = guard.hi - guard.lo
    P = rng.uniform(guard.lo - 0.1 * span, guard.hi + 0.1 * span, (400, len(guard.lo)))
    verdicts = set()
    for k, p_to in enumerate(P):
        p_from = guard.neutral.copy() if k % 2 else np.clip(P[k - 1], guard.lo, guard.hi)
        if k % 50 == 7:
            p_to = p_to.copy()
            p_to[0] = np.nan
        steps = 3 + k % 4
        got, verdict = guard.limit(p_from, p_to, steps=steps)
        ref, ref_verdict = guard.limit_by_checks(p_from, p_to, steps)
        assert verdict == ref_verdict, k
        assert np.array_equal(got, ref, equal_nan=True), k
        verdicts.add(verdict)
    assert verdicts == {"ok", "limited", "held"}


@pytest.mark.skipif(not FEM_SAMPLE.is_file(), reason="no shipped FEM sample")
def test_guard_agrees_with_the_fem_measure_on_the_shipped_sample(guard):
    """FEM surfaces of fresh poses (performances and a random sweep), not used to build the guard."""
    with np.load(FEM_SAMPLE) as z:
        P, offsets, base, faces = z["p"], z["offsets"].astype(np.float64), z["base"], z["faces"]
    rim = load_footprint(ROOT / "heads" / "sample" / "skin_guard.npz", len(faces))
    fem_surface = SurfaceStrain(base, faces, rim, guard.surface.radius, guard.surface.band)
    fem = np.array([fem_surface.extremes(base + o) for o in offsets])
    lo, hi = guard.strain_range
    fem_ok = (fem[:, 0] >= lo) & (fem[:, 1] <= hi)
    assert fem_ok.any() and (~fem_ok).any(), "the sample must hold poses on both sides of the limits"
    full = guard.full_batch(P)
    guard_ok = np.array([guard.check(p) for p in P])
    assert np.mean(guard_ok == fem_ok) >= 0.9
    assert np.median(np.abs(full - fem)) < 0.05


def test_the_fused_solve_and_measure_is_the_solve_then_the_measure(guard):
    """``KsnnInverse.solve(..., measure=guard)``: one compiled call gives the solve's answer and the guard's reduced
    measure of it, as the two separate calls do (and as the numpy path does)."""
    from models.ksnn_solve import KsnnInverse

    sp = guard.predictor
    fast = KsnnInverse(sp.weights, sp.face_unit_offsets)
    ref = KsnnInverse(sp.weights, sp.face_unit_offsets, compiled=False)
    rng = np.random.default_rng(3)
    p_prev = None
    for _ in range(20):
        u = rng.uniform(0.0, 0.7, fast.n_units) * (rng.random(fast.n_units) < 0.2)
        a = fast.solve(u, p_prev=p_prev, max_iterations=3, measure=guard)
        b = fast.solve(u, p_prev=p_prev, max_iterations=3)
        c = ref.solve(u, p_prev=p_prev, max_iterations=3, measure=guard)
        np.testing.assert_array_equal(a.p, b.p)
        assert a.strain == guard.measure_hidden(b.hidden)
        np.testing.assert_allclose(a.strain, c.strain, rtol=0, atol=1e-6)
        assert b.strain is None
        p_prev = a.p


def test_the_fresh_pose_agreement_of_the_report_counts_what_the_check_and_the_full_measure_decide(guard):
    from offline.strain_eval import reduced_agreement

    head = load_head(SAMPLE)
    wide = reduced_agreement(guard, head, 400, seed=1001)
    near = reduced_agreement(guard, head, 400, seed=1002, range_fraction=0.25)
    for rep in (wide, near):
        wrong = rep["check_accepts_full_refuses"] + rep["check_refuses_full_accepts"]
        assert rep["check_vs_full"] == pytest.approx(1 - wrong / 400) and rep["check_vs_full"] >= 0.99
    assert near["full_ok_fraction"] > wide["full_ok_fraction"]  # poses near neutral pass more often
    assert reduced_agreement(guard, head, 400, seed=1001) == wide  # seeded: a rerun measures the same poses


@pytest.mark.parametrize("matrix_rank", [None, 13])
def test_the_frame_solve_from_channel_values_is_the_fused_solve(guard, matrix_rank):
    """``KsnnInverse.frame_solve``: channel values (NaN: not set → 0, clamped to 0..1) give the fused solve's pose,
    iterations and measure of the clamped weights exactly (keeping its Gauss-Newton matrix and last solution across
    frames as the fused solve does with a state of its own, :meth:`KsnnInverse.frame_state`), and the numpy path's
    within rounding; with the exact Gauss-Newton matrix and with the sample head's lower-rank one."""
    from models.ksnn_solve import KsnnInverse

    sp = guard.predictor
    fast = KsnnInverse(sp.weights, sp.face_unit_offsets, matrix_rank=matrix_rank)
    ref = KsnnInverse(sp.weights, sp.face_unit_offsets, compiled=False, matrix_rank=matrix_rank)
    frame = fast.frame_solve(3, 1e-6, 1e-3, guard)
    slow = ref.frame_solve(3, 1e-6, 1e-3, guard)
    assert frame.reuse.frames > 0  # the control frame keeps its matrix
    kept = fast.frame_state(frame.reuse.frames)
    rng = np.random.default_rng(5)
    p_prev = 0.5 * (sp.lo + sp.hi)
    for _ in range(20):
        values = np.where(rng.random(fast.n_units) < 0.2, rng.uniform(-0.3, 1.3, fast.n_units), np.nan)
        values[0] = np.inf
        w = np.where(np.isfinite(values), np.clip(values, 0.0, 1.0), 0.0)
        a = fast.solve(w, p_prev=p_prev, max_iterations=3, tol=1e-6, xtol=1e-3, measure=guard, reuse=kept)
        p = frame(values, p_prev)
        np.testing.assert_array_equal(frame.weights, w)
        np.testing.assert_array_equal(p, a.p)
        assert (frame.iterations, frame.strain, frame.residual_rms) == (a.iterations, a.strain, a.residual_rms)
        q = slow(values, p_prev)
        np.testing.assert_allclose(q, p, rtol=0, atol=1e-12 * np.max(sp.hi - sp.lo))
        np.testing.assert_allclose(slow.strain, frame.strain, rtol=0, atol=1e-6)
        assert frame.reuse.formed == kept.formed == slow.reuse.formed
        p_prev = p.copy()
    assert 0 < frame.reuse.formed < 20 * 3  # matrices were kept, and formed afresh when too old or no help


def test_the_guarded_frame_solve_is_the_solve_then_the_guards_search_in_one_call(guard):
    """With ``guard_steps`` the frame's call also runs the guard: a solution inside the strain range comes back as
    solved ("ok"); one outside it comes back as ``StrainGuard.limit`` from the warm start gives it ("limited" or
    "held") with ``StrainGuard.measure`` of that pose; the numpy path gives the same."""
    from models.ksnn_solve import KsnnInverse

    sp = guard.predictor
    fast = KsnnInverse(sp.weights, sp.face_unit_offsets)
    ref = KsnnInverse(sp.weights, sp.face_unit_offsets, compiled=False)
    frame = fast.frame_solve(3, 1e-6, 1e-3, guard, guard_steps=5)
    slow = ref.frame_solve(3, 1e-6, 1e-3, guard, guard_steps=5)
    kept = fast.frame_state(frame.reuse.frames)
    rng = np.random.default_rng(8)
    p_prev = 0.5 * (sp.lo + sp.hi)
    seen = set()
    for _ in range(150):
        values = np.where(rng.random(fast.n_units) < 0.3, rng.uniform(0.0, 1.0, fast.n_units), np.nan)
        w = np.where(np.isfinite(values), values, 0.0)
        a = fast.solve(w, p_prev=p_prev, max_iterations=3, tol=1e-6, xtol=1e-3, measure=guard, reuse=kept)
        if guard.passes(a.strain):
            want, verdict, strain = a.p, "ok", a.strain
        else:
            want, verdict = guard.limit(p_prev, a.p, 5)
            strain = guard.measure(want)
        p = frame(values, p_prev)
        np.testing.assert_array_equal(p, want)
        assert frame.verdict == verdict
        np.testing.assert_allclose(frame.strain, strain, rtol=0, atol=1e-12)
        q = slow(values, p_prev)
        np.testing.assert_allclose(q, p, rtol=0, atol=1e-9 * np.max(sp.hi - sp.lo))
        assert slow.verdict == verdict
        seen.add(verdict)
        p_prev = p.copy()
    assert {"ok", "limited"} <= seen  # both sides of the guard were exercised
