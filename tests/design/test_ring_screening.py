"""The layout design's ring step on the sample head's skin: on a target made by the skin whose jaw set is one ring
larger, screening at the current actuation must pick exactly that change, and the new nodes move with the jaw."""

from __future__ import annotations

import math

import numpy as np
import pytest

from offline.design.actuation import simulate
from offline.design.mechanism_design import LayoutProblem, LayoutSettings, LayoutState
from offline.design.mechanism_design_envelope import design_space, envelope_from_dict
from offline.design.mechanism_design_rings import RingSettings, RingStep, dry_run_lines, screen
from tests.runtime.conftest import SAMPLE


@pytest.fixture(scope="module")
def case():
    from models.mechanism import load_mechanism
    from offline.design.face import load_face

    face = load_face(SAMPLE)
    spec = load_mechanism(face.skin.head.path("mechanism"))
    env = envelope_from_dict({"attachments": {"jaw": {"rings": 1}, "lower_lip": {"rings": 1}}}, spec, "env.toml")
    space = design_space(spec, env)
    rest = np.asarray(face.mesh.nodes)[face.outer]
    # without the strain penalty: the objective is the match alone, so the change that made the target must win
    lp = LayoutProblem(face, [rest], space, LayoutSettings(), strain=False)
    step = RingStep(lp)
    head = face.skin.head
    p = np.array(head.neutral_pose, dtype=float)
    p[head.actuator_names.index("jaw")] = math.radians(8.0)
    step.set_counts({"jaw": 1})
    x_true = simulate(lp.problem, p)
    assert x_true is not None
    lp.targets = [x_true[lp.problem.region]]  # what the skin with the larger jaw set does at this pose
    step.set_counts({})
    x0 = simulate(lp.problem, p, x_true)
    assert x0 is not None
    w = 0.0
    state = LayoutState(np.zeros(space.size), np.array([lp.aspace.reduce(p)]), [x0], np.array([w]), [])
    return lp, step, state, p


def test_screening_picks_the_change_that_made_the_target(case) -> None:
    lp, step, state, p = case
    assert {k: v for k, v in step.limits.items() if v} == {"jaw": 1, "lower_lip": 1}
    lines = dry_run_lines(step)
    assert any(line.strip().startswith("jaw (jaw) +1 ring: 58 -> ") for line in lines)
    record = screen(step, state, RingSettings(), progress=lambda s: None)
    screened = {(r["node_set"], r["step"]) for r in record["screened"]}
    assert ("jaw", 1) in screened and ("lower_lip", -1) in screened
    assert record["applied"] == [{"node_set": "jaw", "step": 1, "nodes_before": 58,
                                  "nodes_after": record["applied"][0]["nodes_after"]}]
    assert step.counts["jaw"] == 1 and step.counts["lower_lip"] == 0
    assert record["objective_after"] < 1e-3 * record["objective_before"]
    # the skin now solves with the larger set, and its new nodes move rigidly with the jaw
    grown = np.asarray(lp.face.mesh.node_sets["jaw"])
    assert len(grown) == record["applied"][0]["nodes_after"] > 58
    bc = lp.boundary(p)
    T = lp.boundary.transforms(p)["jaw"]
    X = np.asarray(lp.face.mesh.nodes)[grown]
    got = bc.positions[np.searchsorted(bc.nodes, grown)]
    assert np.abs(got - (X @ T[:3, :3].T + T[:3, 3])).max() < 1e-9
    assert np.abs(state.X[0][grown] - got).max() < 1e-9  # the state's equilibria are the new skin's
