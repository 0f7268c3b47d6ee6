"""The layout design's envelope file and design variables: defaults, per-item limits, refusals, projection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.errors import SpecError
from models.mechanism import load_mechanism
from models.mechanism_file import get_param
from offline.design.mechanism_design_envelope import Envelope, design_space, envelope_from_dict, load_envelope
from offline.design.mechanism_design_kin import DesignedMechanism
from tests.runtime.conftest import ROOT

SAMPLE_MECHANISM = ROOT / "heads" / "sample" / "mechanism.toml"


@pytest.fixture(scope="module")
def spec():
    return load_mechanism(SAMPLE_MECHANISM)


def test_the_default_envelope_is_the_documented_one(spec) -> None:
    env = load_envelope(None, spec)
    assert env.joint_move == pytest.approx(0.015)
    assert env.axis_tilt == pytest.approx(math.radians(20))
    assert env.rod_length_rel == pytest.approx(0.2)
    space = design_space(spec, env)
    anchors = [g for g in space.groups if g.what == "anchor"]
    assert len(anchors) == len(spec.joints) and all(g.radius == pytest.approx(0.015) for g in anchors)
    rod = next(g for g in space.groups if g.item == "couplers.jaw_rod" and g.what == "length")
    assert (rod.lo, rod.hi) == (pytest.approx(-0.2 * 0.042), pytest.approx(0.2 * 0.042))


def test_per_item_limits_and_fixed_items_shape_the_variables(spec) -> None:
    env = envelope_from_dict({"envelope": {"joint_move_mm": 5.0},
                              "joints": {"jaw_hinge": {"move_mm": 25.0, "tilt_deg": 0.0}},
                              "couplers": {"jaw_rod": {"fixed": True}}, "motors": {"jaw": {"ratio_rel": 0.1}}},
                             spec, "env.toml")
    space = design_space(spec, env)
    hinge = [g for g in space.groups if g.item == "joints.jaw_hinge"]
    assert [g.what for g in hinge] == ["anchor"] and hinge[0].radius == pytest.approx(0.025)
    assert not [g for g in space.groups if g.item == "couplers.jaw_rod"]
    motor = next(g for g in space.groups if g.item == "motors.jaw")
    assert motor.hi == pytest.approx(0.1 * spec.motors["jaw"].ratio)
    other = next(g for g in space.groups if g.item == "joints.lid_l_hinge" and g.what == "anchor")
    assert other.radius == pytest.approx(0.005)


@pytest.mark.parametrize(("data", "key"), [
    ({"envelope": {"joint_move_mm": -1.0}}, "envelope.joint_move_mm"),
    ({"envelope": {"rod_length_rel": 1.5}}, "envelope.rod_length_rel"),
    ({"envelope": {"attachment_rings": -1}}, "envelope.attachment_rings"),
    ({"envelope": {"attachment_rings": 1.5}}, "envelope.attachment_rings"),
    ({"envelope": {"attachment_rings": True}}, "envelope.attachment_rings"),
    ({"attachments": {"jaw": {"rings": -2}}}, "attachments.jaw.rings"),
    ({"attachments": {"jaw": {"rings": 0.5}}}, "attachments.jaw.rings"),
    ({"attachments": {"no_such_set": {"rings": 1}}}, "attachments.no_such_set"),
    ({"attachments": {"jaw": {"ring": 1}}}, "attachments.jaw"),
    ({"envelope": {"joint_mov_mm": 1.0}}, "envelope.joint_mov_mm"),
    ({"joints": {"no_such_joint": {"fixed": True}}}, "joints.no_such_joint"),
    ({"couplers": {"jaw_rod": {"length_rel": "a lot"}}}, "couplers.jaw_rod.length_rel"),
])
def test_bad_envelopes_are_refused_naming_file_and_key(spec, data, key) -> None:
    with pytest.raises(SpecError) as e:
        envelope_from_dict(data, spec, "env.toml")
    assert e.value.source == "env.toml" and e.value.key == key, str(e.value)


def test_attachment_ring_limits_default_and_per_set(spec) -> None:
    env = envelope_from_dict({"envelope": {"attachment_rings": 2}, "attachments": {"jaw": {"rings": 0}}}, spec,
                             "env.toml")
    limits = env.ring_limits(["jaw", "lower_lip"])
    assert limits == {"jaw": 0, "lower_lip": 2}
    js = env.to_json()
    assert js["attachment_rings"] == 2 and js["attachments"] == {"jaw": 0}
    assert "attachment_rings" not in env.continuous_json()  # the continuous design does not depend on them
    assert load_envelope(None, spec).ring_limits(["jaw"]) == {"jaw": 0}  # off by default: runs are unchanged


def test_an_envelope_file_that_is_missing_or_not_toml_is_refused(spec, tmp_path) -> None:
    with pytest.raises(SpecError, match="not found"):
        load_envelope(tmp_path / "none.toml", spec)
    bad = tmp_path / "bad.toml"
    bad.write_text("[envelope\n")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_envelope(bad, spec)


def test_projection_keeps_every_group_inside_its_ball_or_box(spec) -> None:
    space = design_space(spec, Envelope())
    theta = space.project(np.random.default_rng(0).normal(size=space.size) * 100.0)
    for g in space.groups:
        v = theta[list(g.index)]
        if g.kind == "ball":
            assert np.linalg.norm(v) <= g.radius * (1 + 1e-12)
        else:
            assert g.lo - 1e-15 <= v[0] <= g.hi + 1e-15
    assert {id(g) for g in space.active(theta)} == {id(g) for g in space.groups}


def test_a_design_sets_the_named_parameters_and_the_axis_tilt_is_exact(spec) -> None:
    space = design_space(spec, Envelope())
    theta = np.zeros(space.size)
    tilt = next(g for g in space.groups if g.item == "joints.jaw_hinge" and g.what == "axis")
    rod = next(g for g in space.groups if g.item == "couplers.jaw_rod" and g.what == "length")
    theta[list(tilt.index)] = [math.radians(3.0), math.radians(4.0)]
    theta[rod.index[0]] = 0.001
    new = space.apply(theta)
    angle = math.degrees(math.acos(float(new.joints["jaw_hinge"].axis @ spec.joints["jaw_hinge"].axis)))
    assert angle == pytest.approx(5.0, abs=1e-9)
    assert get_param(new, "couplers.jaw_rod.length") == pytest.approx(0.043)
    # the redesigned mechanism assembles, and at motor zero every link is where the skin is mounted
    dm = DesignedMechanism(space, theta)
    for T in dm.transforms(dm.zero).values():
        assert np.allclose(T, np.eye(4), atol=1e-12)


def test_a_design_that_locks_inside_the_motor_range_is_refused() -> None:
    from models.mechanism import AssemblyError, mechanism_from_dict
    from tests.mechanism._builders import four_bar

    spec = mechanism_from_dict(four_bar())  # a Grashof crank-rocker: the crank turns all the way round
    space = design_space(spec, Envelope())
    full = ({"m": 0.0}, {"m": 2 * math.pi})
    DesignedMechanism(space, np.zeros(space.size)).check_range(*full)
    theta = np.zeros(space.size)
    end = next(g for g in space.groups if g.item == "couplers.coupler" and g.what == "a_point")
    a = spec.couplers["coupler"].a_point
    theta[list(end.index)] = 0.004 * a / np.linalg.norm(a)  # a 24 mm crank: no longer Grashof
    dm = DesignedMechanism(space, theta)  # it assembles at motor zero ...
    with pytest.raises(AssemblyError, match="cannot assemble"):
        dm.check_range(*full)  # ... but not over the whole turn
