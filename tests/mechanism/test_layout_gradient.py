"""The layout design's derivatives on the sample head's skin: the attachment motion's dc/dθ from the mechanism's
implicit derivatives, and the chained gradient of the FEM-simulated objective, each against finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from offline.design.actuation import evaluate
from tests.mechanism._builders import sample_layout

CHECKED = ("joints.jaw_hinge.anchor[1]", "joints.jaw_hinge.axis_tilt[0]", "couplers.jaw_rod.length",
           "couplers.jaw_rod.a_point[2]", "motors.jaw.ratio", "joints.lower_lip_guide.axis_tilt[1]",
           "couplers.lip_corner_l_back_rod.b_point[0]", "couplers.lip_corner_l_turn.ratio")


@pytest.fixture(scope="module")
def layout():
    lp = sample_layout({"jawOpen": 0.5, "mouthSmileLeft": 0.5})
    space = lp.space
    theta = space.project(np.random.default_rng(3).normal(size=space.size) * space.scale * 0.05)
    lp.boundary.set_design(theta)
    head = lp.face.skin.head
    p = np.array(head.neutral_pose, dtype=float)
    for name, deg in (("jaw", 12.0), ("lower_lip", 10.0), ("lip_corner_l_up", 20.0), ("lip_corner_l_back", 15.0)):
        p[head.actuator_names.index(name)] = np.radians(deg)
    return lp, theta, p


def test_attachment_motion_derivatives_match_finite_differences(layout) -> None:
    lp, theta, p = layout
    J = lp.boundary.design_jacobian(p)
    space = lp.space
    for name in CHECKED:
        k = space.names.index(name)
        h = 1e-3 * space.scale[k]
        c = []
        for sign in (1.0, -1.0):
            t = theta.copy()
            t[k] += sign * h
            lp.boundary.set_design(t)
            c.append(lp.boundary(p).dof_values)
        lp.boundary.set_design(theta)
        fd = (c[0] - c[1]) / (2 * h)
        assert np.abs(fd).max() > 0, name  # every checked variable moves some attachment
        assert np.abs(J[:, k] - fd).max() <= 1e-4 * np.abs(fd).max() + 1e-9, name


def test_the_chained_gradient_of_the_fem_objective_matches_finite_differences(layout) -> None:
    lp, theta, p = layout
    pr = lp.problem
    z = lp.aspace.reduce(p)
    target = lp.targets[0]
    w = pr.strain.weight
    ev = evaluate(pr, z, target, None, strain_weight=w)
    assert ev is not None
    lin = lp.linearize(ev, target)
    g = lin.Jt.T @ lin.r  # dE/dθ (the limit penalties do not depend on θ)
    gz = lin.Jz.T @ lin.r
    for name in (CHECKED[0], CHECKED[2], CHECKED[4]):
        k = lp.space.names.index(name)
        h = 0.02 * lp.space.scale[k]
        vals = []
        for sign in (1.0, -1.0):
            t = theta.copy()
            t[k] += sign * h
            lp.boundary.set_design(t)
            e = evaluate(pr, z, target, ev.x, strain_weight=w)
            vals.append(e.value)
        lp.boundary.set_design(theta)
        fd = (vals[0] - vals[1]) / (2 * h)
        assert g[k] == pytest.approx(fd, rel=0.03, abs=1e-3 * np.abs(g).max()), name
    # and one actuation column through the same factorization
    i = int(np.argmax(np.abs(gz)))
    h = 1e-4 * (lp.aspace.zhi[i] - lp.aspace.zlo[i])
    e1, e2 = (evaluate(pr, z + s * h * np.eye(len(z))[i], target, ev.x, strain_weight=w) for s in (1.0, -1.0))
    assert gz[i] == pytest.approx((e1.match + e1.strain_penalty - e2.match - e2.strain_penalty) / (2 * h), rel=0.03)
