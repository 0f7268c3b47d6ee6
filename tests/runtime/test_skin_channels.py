"""arkit.* target channels: solved through a skin predictor, strain-guarded, and played by the daemon on emulators."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from models.predictor import KsnnWeights, SkinPredictor
from runtime.skin import SkinTargetSolver

pytest.importorskip("onnx")
from offline.train.export import export_predictor, predictor_metadata

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"


def grid(n=12, size=0.06):
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def smooth_weights(head, base, amplitude, seed=0, hidden=20) -> KsnnWeights:
    """A KSNN whose hidden units each push a smooth bump of skin (so surface strain scales with ``amplitude``)."""
    rng = np.random.default_rng(seed)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    A = len(lo)
    centers = rng.uniform(0.1, 0.9, (hidden, 2)) * np.ptp(base[:, 0])
    bumps = np.exp(-((base[None, :, :2] - centers[:, None]) ** 2).sum(-1) / (2 * 0.012 ** 2))  # (H, V)
    dirs = rng.normal(size=(hidden, 3))
    W2 = amplitude * np.einsum("hk,hv->khv", dirs, bumps)
    W1 = rng.normal(size=(3, A, hidden)) * 2.0
    b1 = rng.normal(size=(3, hidden)) * 0.2
    w = KsnnWeights(lo, hi, W1, b1, W2, np.zeros((3, base.shape[0])))
    # Like a trained model, predict no offset at the neutral pose (the base mesh is the neutral skin).
    neutral = np.array([a.neutral for a in head.actuators])
    return KsnnWeights(lo, hi, W1, b1, W2, -w.offsets(neutral).T.copy())


def write_predictor(path: Path, head, amplitude=3e-4, unit_poses=None, seed=0) -> SkinPredictor:
    base, faces = grid()
    w = smooth_weights(head, base, amplitude, seed)
    names, offsets = [], []
    for name, p in (unit_poses or {}).items():
        names.append(name)
        offsets.append(w.offsets(p) - w.offsets(np.array([a.neutral for a in head.actuators])))
    meta = predictor_metadata(head=head.name, names=head.actuator_names,
                              units=["rad" if a.kind == "rotary" else "m" for a in head.actuators], weights=w,
                              base_vertices=base, faces=faces, face_unit_names=names,
                              face_unit_offsets=np.array(offsets) if offsets else None)
    export_predictor(path, w, meta)
    return SkinPredictor(path)


@pytest.fixture(scope="module")
def head():
    return load_head(SAMPLE)


def pose(head, **deg):
    p = np.array([a.neutral for a in head.actuators])
    for name, value in deg.items():
        p[head.actuator_names.index(name)] = math.radians(value)
    return p


def test_solver_recovers_the_pose_behind_a_face_unit(tmp_path, head):
    target = pose(head, jaw=15.0, lip_corner_l_up=10.0, brow_r=-8.0)
    sp = write_predictor(tmp_path / "p.onnx", head, unit_poses={"jawOpen": target, "mouthSmileLeft":
                                                                 pose(head, lip_corner_l_up=25.0)})
    solver = SkinTargetSolver.build(head, sp, smoothness=0.0, max_iterations=30)
    assert solver.handles("arkit.jawOpen") and not solver.handles("arkit.nope") and not solver.handles("jaw")
    # The neutral face (all weights 0) is the neutral pose.
    res = solver.solve({"arkit.jawOpen": 0.0}, {})
    np.testing.assert_allclose([res.actuators[n] for n in head.actuator_names], pose(head), atol=1e-3)
    # Held for a few frames (warm-started), the solve lands on the pose that made the unit.
    for _ in range(3):
        res = solver.solve({"arkit.jawOpen": 1.0}, {})
    got = np.array([res.actuators[n] for n in head.actuator_names])
    np.testing.assert_allclose(np.degrees(got), np.degrees(target), atol=0.05)
    assert res.extra["skin_residual_mm"] < 1e-4 and res.extra["skin_guard"] == "ok"
    assert res.extra["skin_iterations"] >= 1 and res.extra["skin_solve_us"] > 0
    # With temporal smoothness the first frame moves less, and holding the target keeps shrinking the residual.
    smooth = SkinTargetSolver.build(head, sp)
    first = smooth.solve({"arkit.jawOpen": 1.0}, {})
    p1 = np.array([first.actuators[n] for n in head.actuator_names])
    assert np.linalg.norm(p1 - pose(head)) < np.linalg.norm(got - pose(head))
    for _ in range(10):
        later = smooth.solve({"arkit.jawOpen": 1.0}, {})
    assert later.extra["skin_residual_mm"] < first.extra["skin_residual_mm"]


def test_strain_guard_keeps_poses_within_the_validated_range(tmp_path, head):
    sp = write_predictor(tmp_path / "p.onnx", head, amplitude=2e-3, seed=3, unit_poses={"x": pose(head)})
    solver = SkinTargetSolver.build(head, sp)
    rng = np.random.default_rng(0)
    P = rng.uniform(solver.lo, solver.hi, size=(300, len(solver.lo)))
    strains = np.array([solver.strain(p) for p in P])
    ok = (strains[:, 0] >= -0.2) & (strains[:, 1] <= 0.5)
    assert ok.any() and (~ok).any(), "the test model must have safe and unsafe poses"
    safe, unsafe = P[np.flatnonzero(ok)[0]], P[np.flatnonzero(~ok)[0]]
    solver.reset(dict(zip(head.actuator_names, safe, strict=True)))
    p, outcome, strain = solver.guard(unsafe)
    assert outcome in ("limited", "held")
    assert strain[0] >= -0.2 and strain[1] <= 0.5
    assert solver.strain(p)[0] >= -0.2 and solver.strain(p)[1] <= 0.5
    assert np.linalg.norm(p - safe) < np.linalg.norm(unsafe - safe)
    p2, outcome2, _ = solver.guard(safe)
    assert outcome2 == "ok" and np.array_equal(p2, safe)


def test_predictor_without_face_units_or_for_another_head_is_refused(tmp_path, head):
    from models.errors import SpecError

    sp = write_predictor(tmp_path / "p.onnx", head)
    with pytest.raises(SpecError, match="face_units"):
        SkinTargetSolver.build(head, sp)
    other = load_head(SAMPLE)
    import dataclasses

    acts = list(other.actuators)
    other = dataclasses.replace(other, actuators=(dataclasses.replace(acts[0], name="mandible"), *acts[1:]))
    sp2 = write_predictor(tmp_path / "q.onnx", head, unit_poses={"jawOpen": pose(head, jaw=5)})
    with pytest.raises(SpecError, match="jaw"):
        SkinTargetSolver.build(other, sp2)


def test_daemon_plays_blendshape_curves_through_the_predictor(tmp_path, head, make_daemon):
    from models.client import Client, Telemetry
    from tests._wait import wait_until

    # The sample's attachment distances belong to its own skin, not to this test predictor's grid.
    text = SAMPLE.read_text()
    (tmp_path / "head.toml").write_text("\n".join(ln for ln in text.splitlines() if not ln.startswith("skin_guard")))
    target = pose(head, jaw=12.0, upper_lip=6.0)
    write_predictor(tmp_path / "predictor.onnx", head, unit_poses={"jawOpen": target,
                                                                    "browInnerUp": pose(head, brow_l=10, brow_r=10)})
    d = make_daemon(tmp_path / "head.toml", target_solvers=None)  # None: solvers from the head config
    clip = {"name": "talk", "channels": {"arkit.jawOpen": {"interp": "linear", "keys": [[0, 0], [0.4, 1], [1.4, 1]]}}}
    with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint) as tel:
        c.call("enable")
        c.call("load_clip", clip=clip)
        start = c.call("play", clip="talk")["start"]
        extras = []
        for topic, msg in tel.iter(3.0):
            if topic == "state" and msg["t"] >= start and "extra" in msg:
                extras.append(msg["extra"])
            if topic == "event" and msg.get("event") == "clip" and msg.get("state") == "finished":
                break
        st = wait_until(lambda: (lambda s: s if not s["moving"] else None)(c.call("status")), 30)
        assert st and st["fault"] is None
        assert st["commanded"]["jaw"] == pytest.approx(12.0, abs=1.0)
        assert st["commanded"]["upper_lip"] == pytest.approx(6.0, abs=1.0)
        assert math.degrees(d.hw.simulated_positions()["jaw"]) == pytest.approx(12.0, abs=1.5)
        assert extras and all("skin_residual_mm" in e for e in extras)
        assert extras[-1]["skin_residual_mm"] < 0.05
        c.call("disable")


def test_predictor_trained_on_part_of_the_range_solves_within_it(tmp_path, head):
    import dataclasses

    narrow = dataclasses.replace(head, actuators=tuple(
        dataclasses.replace(a, min=a.neutral - 0.1 * (a.max - a.min) if a.neutral > a.min else a.min,
                            max=a.neutral + 0.1 * (a.max - a.min)) for a in head.actuators))
    far = pose(head, jaw=25.0, brow_l=30.0)  # outside the trained range
    edge = np.clip(far, sp_lo(narrow), sp_hi(narrow))
    sp = write_predictor(tmp_path / "p.onnx", narrow, unit_poses={"jawOpen": edge})
    solver = SkinTargetSolver.build(head, sp, smoothness=0.0, max_iterations=30)
    np.testing.assert_allclose(solver.hi, sp.hi)
    for _ in range(5):
        res = solver.solve({"arkit.jawOpen": 1.0}, {})
    got = np.array([res.actuators[n] for n in head.actuator_names])
    assert np.all(got <= sp.hi + 1e-9) and np.all(got >= sp.lo - 1e-9)
    np.testing.assert_allclose(got, edge, atol=1e-3)  # the reachable target at the edge of the trained range


def sp_lo(h):
    return np.array([a.min for a in h.actuators])


def sp_hi(h):
    return np.array([a.max for a in h.actuators])


def test_shipped_sample_predictor_drives_the_sample_head(head):
    """The predictor shipped with the sample head: 52 face units, jawOpen opens the jaw."""
    import json

    solver = SkinTargetSolver.from_head(head)
    assert solver is not None and len(solver.units) == 52 and solver.handles("arkit.jawOpen")
    rest = solver.solve({"arkit.jawOpen": 0.0}, {})
    report = json.loads((head.source.parent / "predictor_report.json").read_text())
    # The neutral face is reached from the neutral pose, up to the predictor's own held-out error.
    assert rest.extra["skin_residual_mm"] < 2e-3 * report["test"]["rms_euclidean_um"]
    for _ in range(10):
        res = solver.solve({"arkit.jawOpen": 0.05}, {})
    jaw = head.actuator_names.index("jaw")
    assert res.actuators["jaw"] > rest.actuators["jaw"] + 0.005
    assert solver.lo[jaw] - 1e-9 <= res.actuators["jaw"] <= solver.hi[jaw] + 1e-9
    assert res.extra["skin_guard"] == "ok"
    w = np.zeros(52)
    w[solver.units["jawOpen"]] = 0.05
    staying_put_mm = np.sqrt(solver.inverse.surface_error(solver.neutral, w)) * 1e3
    assert res.extra["skin_residual_mm"] < 0.8 * staying_put_mm  # the solve matches the target better than neutral


def test_skin_table_of_the_head_tunes_the_solver_and_is_validated(tmp_path, head, caplog):
    import dataclasses

    from models.errors import SpecError

    tuned = dataclasses.replace(head, sections={**head.sections, "skin": {"strain_max": 0.3, "smoothness_mm": 0.0,
                                                                         "iterations_per_frame": 5,
                                                                         "matrix_rank": 8}})
    solver = SkinTargetSolver.from_head(tuned)
    assert solver.strain_range == (-0.2, 0.3) and solver.inverse.smoothness == 0.0 and solver.max_iterations == 5
    assert solver.inverse.matrix_rank == 8 < solver.inverse.rank
    assert "matrix_rank = 8 is below the head's" in caplog.text  # fewer rows than actuators: warned
    for bad, key in (({"strain_max": "a lot"}, "skin.strain_max"), ({"strain_min": 0.1}, "skin.strain_min"),
                     ({"iterations_per_frame": 0}, "skin.iterations_per_frame"), ({"colour": 1}, "skin.colour"),
                     ({"matrix_rank": 0}, "skin.matrix_rank"), ({"matrix_rank": 2.5}, "skin.matrix_rank")):
        with pytest.raises(SpecError, match=key.replace(".", r"\.")):
            SkinTargetSolver.from_head(dataclasses.replace(head, sections={**head.sections, "skin": bad}))


def test_reset_forgets_the_warm_start_and_channels_are_declared(tmp_path, head):
    from models.strain_guard import StrainGuard

    sp = write_predictor(tmp_path / "p.onnx", head, unit_poses={"jawOpen": pose(head, jaw=15.0, upper_lip=5.0)})
    solver = SkinTargetSolver.build(head, sp)
    assert isinstance(solver.strain_guard, StrainGuard)
    assert solver.channels() == {"arkit.jawOpen": "weight"}
    fresh = SkinTargetSolver.build(head, sp).solve({"arkit.jawOpen": 1.0}, {})
    for _ in range(5):
        warm = solver.solve({"arkit.jawOpen": 1.0}, {})
    assert warm.actuators["jaw"] > fresh.actuators["jaw"] + 1e-3  # the warm start carried the solve further
    solver.reset()
    again = solver.solve({"arkit.jawOpen": 1.0}, {})
    assert again.actuators == pytest.approx(fresh.actuators, abs=1e-12)
    assert again.extra["skin_guard"] == "ok"


def test_the_array_path_and_the_mapping_api_give_the_same_targets(head):
    """``solve_array`` (the core's per-cycle call) and ``solve`` (by name) are the same solve: the same actuator
    values and telemetry on random sparse frames (NaN: not set; values outside 0..1 clamped), across guard
    limits and resets; the core takes the solver in its array form."""
    from runtime.core.channels import ChannelMap
    from runtime.core.solvers import as_array_solvers, channel_sets

    by_name = SkinTargetSolver.from_head(head)
    by_array = SkinTargetSolver.from_head(head)
    assert by_name is not None and by_array is not None
    cm = ChannelMap.build(head, channel_sets([by_array]))
    assert as_array_solvers([by_array], cm.target_blocks, cm.names, head.actuator_names) == [by_array]
    channels = list(by_array.channels())
    rng = np.random.default_rng(7)
    guards = set()
    for k in range(300):
        block = np.where(rng.random(len(channels)) < 0.15, rng.uniform(-0.2, 1.3, len(channels)), np.nan)
        if k % 50 == 49:
            q = rng.uniform(by_array.lo, by_array.hi)
            q[0] = np.nan
            by_array.reset_array(q)
            by_name.reset({n: float(v) for n, v in zip(head.actuator_names, q, strict=True)})
        got, extra = by_array.solve_array(block, np.zeros(len(head.actuators)))
        ref = by_name.solve({ch: float(v) for ch, v in zip(channels, block, strict=True) if v == v}, {})
        np.testing.assert_array_equal(got, [ref.actuators[n] for n in head.actuator_names])
        plain = dict(extra)
        assert plain.pop("skin_solve_us") > 0 and ref.extra.pop("skin_solve_us") > 0
        assert plain == ref.extra
        guards.add(plain["skin_guard"])
    assert "ok" in guards
