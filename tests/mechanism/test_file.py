"""The mechanism file refuses bad input at load, naming the file, the key and why."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest

from models.errors import SpecError
from models.headspec import load_head
from models.mechanism import SAMPLE_MECHANISM, Mechanism, load_mechanism, mechanism_from_dict
from tests.mechanism._builders import four_bar

SAMPLE_HEAD = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def _refused(doc, key: str, why: str) -> None:
    with pytest.raises(SpecError, match=why) as info:
        mechanism_from_dict(doc, source="m.toml")
    assert info.value.key == key
    assert str(info.value).startswith(f"m.toml: {key}: ")


def test_a_mechanism_that_does_not_close_at_neutral_is_refused() -> None:
    doc = four_bar()
    doc["couplers"]["coupler"]["length"] += 0.5e-3
    _refused(doc, "couplers.coupler.length", r"does not close at neutral.*gap -0\.5000 mm")


def test_a_joint_outside_its_body_is_refused() -> None:
    doc = four_bar()
    doc["joints"]["rocker_pivot"]["anchor"] = [0.04, 0.04, 0.0]
    _refused(doc, "joints.rocker_pivot.anchor", r"40\.0 mm from the origin of its child 'rocker', beyond its extent "
             r"36\.0 mm")
    doc = four_bar()
    doc["couplers"]["coupler"]["a_point"] = [0.0, 0.1, 0.0]
    _refused(doc, "couplers.coupler.a_point", "beyond its extent")


def test_a_motor_on_a_passive_joint_is_refused() -> None:
    doc = four_bar()
    doc["motors"]["m"]["joint"] = "rocker_pivot"
    _refused(doc, "motors.m.joint", r"joint 'rocker_pivot' is passive \(actuated = false\)")
    doc = four_bar()
    doc["joints"]["ball"] = {"kind": "spherical", "parent": "frame", "child": "rocker", "anchor": [0.04, 0.0, 0.0],
                             "actuated": True}
    doc["motors"]["m2"] = {"joint": "ball"}
    _refused(doc, "motors.m2.joint", "is spherical, not revolute or prismatic")


def test_a_loop_with_too_few_constraints_is_refused() -> None:
    doc = four_bar()
    del doc["couplers"]["coupler"]  # the rocker swings freely on its pivot
    _refused(doc, "bodies.rocker", r"too few constraints.*rocker can still move \(1 degree\(s\) of freedom left\)")
    doc = four_bar()
    doc["bodies"]["loose"] = {"origin": [0.0, 0.0, 0.0], "extent": 0.01}
    _refused(doc, "bodies.loose", r"loose can still move \(6 degree")


def test_unknown_keys_names_and_kinds_are_refused() -> None:
    doc = four_bar()
    doc["joints"]["crank_pivot"]["axiss"] = [0, 0, 1]
    _refused(doc, "joints.crank_pivot.axiss", "unknown field")
    doc = four_bar()
    doc["joints"]["crank_pivot"]["kind"] = "hinge"
    _refused(doc, "joints.crank_pivot.kind", "must be one of revolute, prismatic, spherical, fixed")
    doc = four_bar()
    doc["couplers"]["coupler"]["b"] = "rokker"
    _refused(doc, "couplers.coupler.b", "names no body")
    doc = four_bar()
    doc["joints"]["crank_pivot"]["axis"] = [0, 0, 0]
    _refused(doc, "joints.crank_pivot.axis", "must not be zero")
    doc = copy.deepcopy(four_bar())
    doc["joints"]["crank_pivot"]["actuated"] = True
    del doc["motors"]["m"]
    _refused(doc, "joints.crank_pivot.actuated", "needs a motor")


def test_the_sample_file_loads_and_matches_the_head(tmp_path) -> None:
    head = load_head(SAMPLE_HEAD)
    assert head.path("mechanism") == SAMPLE_MECHANISM
    mech = Mechanism.load(SAMPLE_MECHANISM)
    mech.check_against(head)
    data = tomllib.loads(SAMPLE_MECHANISM.read_text())
    del data["motors"]["brow_r"]
    data["joints"]["brow_r_crank"]["actuated"] = False
    bad = tmp_path / "mechanism.toml"
    with pytest.raises(SpecError, match="too few constraints"):
        mechanism_from_dict(data, source=str(bad))
    with pytest.raises(SpecError, match="mechanism file not found"):
        load_mechanism(tmp_path / "missing.toml")
