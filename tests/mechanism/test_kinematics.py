"""Forward kinematics of mechanism files: closure, Jacobians, implicit derivatives, branches, assembly errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.mechanism import AssemblyError, Mechanism, mechanism_from_dict
from models.mechanism_file import get_param, with_params
from models.mechanism_kin import State, _apply, group_residual, revolute_angle, structure
from models.rigid import matrix_to_rotvec
from tests.mechanism._builders import every_kind, four_bar

DEG = math.pi / 180


def _rocker_closed_form(q: float, ground=0.040, crank=0.020, coupler=0.042, rocker=0.024, crank0=100 * DEG) -> float:
    """The rocker angle of a four-bar by circle intersection (the branch above the ground line)."""
    A = crank * np.array([math.cos(crank0 + q), math.sin(crank0 + q)])
    O4 = np.array([ground, 0.0])
    d = float(np.linalg.norm(O4 - A))
    a = (coupler**2 - rocker**2 + d**2) / (2 * d)
    e = (O4 - A) / d
    B = A + a * e + math.sqrt(coupler**2 - a**2) * np.array([-e[1], e[0]])
    return math.atan2(B[1], B[0] - ground)


def test_four_bar_matches_its_closed_form_over_a_full_crank_turn() -> None:
    mech = Mechanism(mechanism_from_dict(four_bar()))
    r0 = _rocker_closed_form(0.0)
    for q in np.linspace(0.0, 2 * math.pi, 25):  # a Grashof crank-rocker: the crank turns all the way round
        T = mech.transforms({"m": q})["rocker"]
        turn = matrix_to_rotvec(T[:3, :3])[2]
        assert turn == pytest.approx(_rocker_closed_form(q) - r0, abs=1e-9)
    back = mech.transforms({"m": 0.0})["rocker"]  # and comes back to the same branch
    assert np.allclose(back, np.eye(4), atol=1e-10)


def test_constraint_jacobians_match_finite_differences() -> None:
    spec = mechanism_from_dict(every_kind())
    st = structure(spec)
    rng = np.random.default_rng(3)
    state = State.neutral(len(st.bodies))
    for g in st.groups:
        _apply(g, state, rng.normal(0, 0.05, g.size))  # a state off the solution, rotations of a few degrees
    targets = {"m": 0.1, "s": -0.05}
    h = 1e-6
    for g in st.groups:
        _, J = group_residual(g, state, targets)
        Jfd = np.zeros_like(J)
        for k in range(g.size):
            for sign in (1, -1):
                s2 = state.copy()
                dx = np.zeros(g.size)
                dx[k] = sign * h
                _apply(g, s2, dx)
                Jfd[:, k] += sign * group_residual(g, s2, targets, jacobian=False)[0] / (2 * h)
        assert np.max(np.abs(J - Jfd)) < 2e-5 * max(1.0, np.abs(J).max()), np.unravel_index(
            np.argmax(np.abs(J - Jfd)), J.shape)


def test_every_joint_kind_solves_and_keeps_its_geometry() -> None:
    spec = mechanism_from_dict(every_kind())
    mech = Mechanism(spec)
    T = mech.body_transforms({"m": 20 * DEG, "s": 15 * DEG})
    j = spec.joints
    # revolute: the pivot stays put and the rocker turns about z only
    assert np.allclose(T["rocker"][:3, :3] @ j["rocker_pivot"].anchor + T["rocker"][:3, 3], j["rocker_pivot"].anchor)
    assert abs(revolute_angle(j["crank_pivot"], np.eye(3), T["crank"][:3, :3]) - 20 * DEG) < 1e-10
    # spherical: the ball's centre stays put; fixed: the plate moves with the arm
    assert np.allclose(T["arm"][:3, :3] @ j["ball"].anchor + T["arm"][:3, 3], j["ball"].anchor, atol=1e-12)
    assert np.allclose(T["plate"], T["arm"], atol=1e-12)
    # rods keep their lengths
    for c in spec.couplers.values():
        if c.kind == "rod":
            pa = T[c.a][:3, :3] @ c.a_point + T[c.a][:3, 3]
            pb = T[c.b][:3, :3] @ c.b_point + T[c.b][:3, 3]
            assert np.linalg.norm(pa - pb) == pytest.approx(c.length, abs=1e-12)
    # the slider moved along its guide and rocked with it
    rel = np.linalg.inv(T["rocker"]) @ T["slider"]
    travel = float(j["slide"].axis @ (rel[:3, :3] @ j["slide"].anchor + rel[:3, 3] - j["slide"].anchor))
    assert abs(travel) > 1e-4
    rock = matrix_to_rotvec(rel[:3, :3])
    assert np.allclose(rock, j["slide"].tilt_axis * j["slide"].tilt_rate * travel, atol=1e-10)


@pytest.mark.parametrize("doc", [four_bar, every_kind], ids=["four-bar", "every-kind"])
def test_implicit_derivatives_match_finite_differences_of_the_solve(doc) -> None:
    spec = mechanism_from_dict(doc())
    q = {"m": 30 * DEG, "s": 10 * DEG} if "s" in spec.motors else {"m": 30 * DEG}
    params = ["joints.rocker_pivot.anchor[0]", "joints.crank_pivot.anchor[1]", "couplers.coupler.length",
              "couplers.coupler.b_point[1]"]
    d_act, d_par = Mechanism(spec).jacobian(q, params)
    h = 1e-6

    def poses(s, qq):
        return Mechanism(s).link_poses(qq)

    def fd(plus, minus):  # position difference, and the rotation increment in the head frame
        return np.concatenate([plus[:3, 3] - minus[:3, 3], matrix_to_rotvec(plus[:3, :3] @ minus[:3, :3].T)]) / (2 * h)

    for k, a in enumerate(spec.motor_names):
        plus = poses(spec, {**q, a: q[a] + h})
        minus = poses(spec, {**q, a: q[a] - h})
        for n in plus:
            assert np.allclose(d_act[n][:, k], fd(plus[n], minus[n]), atol=1e-6), (n, a)
    for k, p in enumerate(params):
        v = get_param(spec, p)
        plus, minus = (poses(with_params(spec, {p: v + s * h}), q) for s in (1, -1))
        for n in plus:
            assert np.allclose(d_par[n][:, k], fd(plus[n], minus[n]), atol=1e-5), (n, p)
        assert any(np.abs(d_par[n][:, k]).max() > 1e-3 for n in d_par), p  # the parameter matters


def test_a_linkage_that_cannot_assemble_names_the_loop_and_the_motor_values() -> None:
    # not Grashof: the crank cannot turn all the way; past its dead point the rod is too short
    spec = mechanism_from_dict(four_bar(ground=0.040, crank=0.030, coupler=0.030, rocker=0.024, crank0_deg=60))
    mech = Mechanism(spec)
    mech.link_poses({"m": 10 * DEG})
    with pytest.raises(AssemblyError, match=r"loop of crank, rocker \(couplers coupler\).*m=150\.000 deg"):
        mech.link_poses({"m": 150 * DEG})
    assert np.isfinite(mech.link_poses({"m": 5 * DEG})["rocker"]).all()  # still usable afterwards


def test_hard_stops_and_zero_error_act_before_the_linkage() -> None:
    spec = mechanism_from_dict(four_bar())
    mech = Mechanism(spec, zero_error={"m": 2 * DEG}, stops={"m": (-10 * DEG, 20 * DEG)})
    assert np.allclose(mech.link_poses({"m": 2 * DEG})["rocker"], mech.rest_poses()["rocker"], atol=1e-12)
    assert np.allclose(mech.link_poses({"m": 22 * DEG})["rocker"], mech.link_poses({"m": 40 * DEG})["rocker"])
    d_act, _ = mech.jacobian({"m": 40 * DEG})
    assert np.all(d_act["rocker"] == 0.0)  # held at the stop: the motor no longer moves the link
