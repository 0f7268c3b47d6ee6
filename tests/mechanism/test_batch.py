"""The mechanism solved at many motor values at once agrees with the pose-by-pose path: residuals, Jacobians,
solutions (the same assembly branch), implicit derivatives and assembly errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models import mechanism_batch as mb
from models import mechanism_kin as mk
from models.headspec import load_head
from models.mechanism import SAMPLE_MECHANISM, AssemblyError, Mechanism, load_mechanism, mechanism_from_dict
from sim_hardware.mechanism import sample_mechanism
from tests.mechanism._builders import every_kind, four_bar
from tests.mechanism.test_file import SAMPLE_HEAD

DEG = math.pi / 180


@pytest.mark.parametrize("which", ["every-kind", "sample"])
def test_stacked_residuals_and_jacobians_are_the_single_pose_ones(which) -> None:
    spec = mechanism_from_dict(every_kind()) if which == "every-kind" else load_mechanism(SAMPLE_MECHANISM)
    st = mk.structure(spec)
    rng = np.random.default_rng(4)
    states = []
    for _ in range(5):  # states off the solution: rotations of a few degrees, millimetres of translation
        s = mk.State.neutral(len(st.bodies))
        for g in st.groups:
            mk._apply(g, s, rng.normal(0, 0.05, g.size))
        states.append(s)
    R, t = np.stack([s.R for s in states]), np.stack([s.t for s in states])
    targets = {m: rng.uniform(-0.3, 0.3, len(states)) * (0.05 if spec.joints[spec.motors[m].joint].kind ==
                                                         "prismatic" else 1.0) for m in spec.motors}
    for g in st.groups:
        r, J = mb.group_residual(g, R, t, targets)
        for i, s in enumerate(states):
            ri, Ji = mk.group_residual(g, s, {m: float(v[i]) for m, v in targets.items()})
            assert np.abs(r[i] - ri).max() < 1e-14
            assert np.abs(J[i] - Ji).max() < 1e-13


def test_many_poses_solve_as_one_at_a_time_on_the_sample_head_on_the_same_branch() -> None:
    """The emulated head (zero errors, hard stops): every pose straight from neutral, vectorised, against the
    sequential path from the previous pose; a branch jump would differ by millimetres."""
    head = load_head(SAMPLE_HEAD)
    mech = sample_mechanism(head, seed=5)
    names = list(head.actuator_names)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    rng = np.random.default_rng(3)
    P = np.vstack([lo, hi, 1.3 * hi, rng.uniform(lo, hi, (40, len(names)))])  # 1.3 × max: beyond the stops
    many = mech.link_poses_many(names, P)
    worst = 0.0
    for i, p in enumerate(P):
        one = mech.link_poses(dict(zip(names, p, strict=True)))
        for n, T in one.items():
            worst = max(worst, float(np.abs(many[n][i] - T).max()))
    assert worst < 1e-9, worst
    R, t = mech.solve_many(names, P[3:5])
    for k, p in enumerate(P[3:5]):
        s = mech.solve(dict(zip(names, p, strict=True)))
        assert np.abs(R[k] - s.R).max() < 1e-9 and np.abs(t[k] - s.t).max() < 1e-9


def test_implicit_derivatives_at_many_poses_are_the_single_pose_ones() -> None:
    spec = mechanism_from_dict(every_kind())
    mech = Mechanism(spec)
    st = mech.structure
    names = list(spec.motor_names)
    P = np.array([[0.1, -0.01], [-0.2, 0.02], [0.3, 0.0]])
    params = ["couplers.push.length", "joints.slide.anchor[1]", "couplers.arm_gear.ratio"]
    R, t = mech.solve_many(names, P)
    goal = mech.joint_targets_many(names, P)
    for g in st.groups:
        dq, dp = mb.state_derivatives(st, g, R, t, goal, params)
        for i, p in enumerate(P):
            state = mech.solve(dict(zip(names, p, strict=True)))
            one = mk.joint_targets(spec, mech.joint_angles(dict(zip(names, p, strict=True))))
            dq1, dp1 = mk.state_derivatives(st, g, state, one, params)
            assert np.abs(dq[i] - dq1).max() < 1e-6 * max(1.0, np.abs(dq1).max())
            assert np.abs(dp[i] - dp1).max() < 1e-6 * max(1.0, np.abs(dp1).max())
            for body in st.bodies:
                a = mb.body_jacobian(st, R, body, dp, g)[i]
                assert np.abs(a - mk.body_jacobian(st, state, body, dp1, g)).max() < 1e-6 * max(1.0, np.abs(a).max())


def test_a_pose_that_cannot_assemble_raises_as_the_single_pose_path_does() -> None:
    spec = mechanism_from_dict(four_bar(ground=0.040, crank=0.030, coupler=0.030, rocker=0.024, crank0_deg=60))
    mech = Mechanism(spec)
    fine = mech.link_poses_many(["m"], np.array([[5 * DEG], [10 * DEG]]))["rocker"]
    assert np.isfinite(fine).all()
    with pytest.raises(AssemblyError, match=r"loop of crank, rocker \(couplers coupler\).*m=150\.000 deg"):
        mech.link_poses_many(["m"], np.array([[10 * DEG], [150 * DEG]]))
