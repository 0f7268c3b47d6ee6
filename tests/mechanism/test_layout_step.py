"""A layout design step that would break one linkage loop's assembly: only that loop's part of the step is cut, the
other loops take theirs whole (before, the whole step was damped until every loop assembled, and the design stopped
after a few percent)."""

from __future__ import annotations

import numpy as np
import pytest

from models.mechanism_kin import AssemblyError
from offline.design.mechanism_design import LayoutState, _assembling_step
from tests.mechanism._builders import sample_layout

LID_L = ("lid_l", "lid_l_crank")


@pytest.fixture(scope="module")
def layout():
    return sample_layout({"eyeBlinkLeft": 0.5, "jawOpen": 0.2})


def test_a_loop_names_the_variables_that_act_on_it(layout) -> None:
    space = layout.space
    lid = [space.names[i] for i in np.flatnonzero(space.touching(LID_L))]
    assert "couplers.lid_l_rod.length" in lid and "motors.lid_l.ratio" in lid
    assert "joints.lid_l_hinge.anchor[0]" in lid and "joints.lid_l_crank.axis_tilt[1]" in lid
    assert all("lid_l" in n for n in lid)  # nothing of the right lid, the jaw or the lips


def test_only_the_loop_that_breaks_has_its_step_cut(layout) -> None:
    lp = layout
    space = lp.space
    head = lp.face.skin.head
    lo = {a.name: a.min for a in head.actuators}
    hi = {a.name: a.max for a in head.actuators}
    d = np.zeros(space.size)
    lid = space.names.index("couplers.lid_l_rod.a_point[0]")
    jaw = space.names.index("joints.jaw_hinge.anchor[1]")
    d[lid] = 3 * space.scale[lid]  # the left lid's four-bar no longer assembles over its motor's range
    d[jaw] = 1 * space.scale[jaw]
    from offline.design.mechanism_design_kin import DesignedMechanism

    with pytest.raises(AssemblyError) as err:
        DesignedMechanism(space, space.project(d)).check_range(lo, hi)
    assert set(err.value.bodies) == set(LID_L)
    z = lp.aspace.reduce(np.array(head.neutral_pose, dtype=float))[None]
    state = LayoutState(np.zeros(space.size), z, [None], np.array([lp.problem.strain.weight]), [])
    theta, trial = _assembling_step(lp, state.theta, d, z, state)
    assert trial is not None  # evaluated: the design assembles
    assert theta[jaw] == pytest.approx(d[jaw])  # the jaw's part of the step taken whole
    assert abs(theta[lid]) < d[lid] / 3  # the lid's cut (by 4 each time, or dropped)
    assert state.held_back == {"lid_l, lid_l_crank": state.held_back["lid_l, lid_l_crank"]}
    DesignedMechanism(space, theta).check_range(lo, hi)
