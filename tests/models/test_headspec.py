"""Head spec loading: the sample head loads, bad specs fail naming file, key and value."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from models.errors import SpecError
from models.headspec import head_from_dict, load_head

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def sample_dict() -> dict:
    return tomllib.loads(SAMPLE.read_text())


def test_sample_head_loads_in_si() -> None:
    head = load_head(SAMPLE)
    assert len(head.actuators) == 13
    jaw = head.actuator("jaw")
    assert jaw.kind == "rotary"
    assert math.isclose(jaw.max, math.radians(28.0))
    assert math.isclose(jaw.max_velocity, math.radians(180.0))
    assert {b.driver for b in head.buses.values()} == {"canopen402", "dynamixel"}
    coupled = [g for g in head.groups if g.kind == "coupled"]
    assert coupled and math.isclose(coupled[0].max_spread, math.radians(45.0))
    assert head.path("linkmap") == SAMPLE.parent / "linkmap.json"
    assert any(link.rigid for link in head.links)


@pytest.mark.parametrize(
    ("mutate", "key_fragment"),
    [
        (lambda d: d["actuators"][0].update(bus="nope"), "actuators[0] (jaw).bus"),
        (lambda d: d["actuators"][1].update(id=1), "actuators[1] (lip_corner_l_up).id"),
        (lambda d: d["actuators"][0].update(unit="furlong"), "actuators[0] (jaw).unit"),
        (lambda d: d["actuators"][0].update(min=50.0), "actuators[0] (jaw).min"),
        (lambda d: d["actuators"][0].update(max_velocity=float("nan")), "max_velocity"),
        (lambda d: d["actuators"][0].update(colour="red"), "actuators[0] (jaw).colour"),
        (lambda d: d["actuators"][0].pop("bus"), "actuators[0] (jaw).bus"),
        (lambda d: d["groups"]["blink"].update(actuators=["lid_l", "ghost"]), "groups.blink.actuators"),
        (lambda d: d["links"]["jaw"].update(actuators=[]), "links.jaw.actuators"),
        (lambda d: d["buses"]["can0"].pop("driver"), "buses.can0.driver"),
        (lambda d: d.update(actuators=[]), "actuators"),
    ],
)
def test_bad_specs_name_the_key(mutate, key_fragment: str) -> None:
    data = sample_dict()
    mutate(data)
    with pytest.raises(SpecError) as info:
        head_from_dict(data, source="bad.toml")
    assert "bad.toml" in str(info.value)
    assert key_fragment in str(info.value)


def test_unreadable_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match="cannot read"):
        load_head(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[head\nname=")
    with pytest.raises(SpecError, match="not valid TOML"):
        load_head(bad)


def _with_material(table: dict) -> dict:
    data = tomllib.loads(SAMPLE.read_text())
    data["skin_material"] = table
    return data


def test_skin_material_inline_and_its_errors(tmp_path: Path) -> None:
    head = head_from_dict(_with_material({"model": "Mooney-Rivlin", "E": 70_000, "nu": 0.46, "c01": 5000.0,
                                          "note": "why"}), tmp_path / "h.toml")
    mat = head.skin_material()
    assert mat.model == "mooney_rivlin" and mat.E == 70_000.0 and dict(mat.shape) == {"c01": 5000.0}
    assert "inline [skin_material] in h.toml" in mat.source and mat.note == "why"
    for table, fragment in [
        ({"model": "neo_hookean", "E": 1e5}, "skin_material.nu: required"),
        ({"model": "rubber", "E": 1e5, "nu": 0.4}, "unknown material model 'rubber'"),
        ({"model": "neo_hookean", "E": 1e5, "nu": 0.5}, "nu must lie in"),
        ({"model": "neo_hookean", "E": "soft", "nu": 0.4}, "skin_material.E: must be a number"),
        ({"model": "neo_hookean", "E": 1e5, "nu": 0.4, "c01": 1.0}, "has no parameter c01"),
        ({"model": "neo_hookean", "E": 1e5, "nu": 0.4, "colour": "pink"}, "skin_material.colour: unknown key"),
        ({"fit": "fit.json", "E": 1e5}, "give either fit = FILE or inline parameters"),
        ({"fit": "fit.json", "nu": "0.4"}, "skin_material.nu: must be a number"),
    ]:
        with pytest.raises(SpecError, match=fragment):
            head_from_dict(_with_material(table), tmp_path / "h.toml")
    # A fit file is read when the material is asked for, not when the head loads (the daemon never needs it).
    head = head_from_dict(_with_material({"fit": "missing.json"}), tmp_path / "h.toml")
    with pytest.raises(SpecError, match=r"missing\.json: file: cannot read material fit"):
        head.skin_material()
    (tmp_path / "other.json").write_text('{"format": "something-else"}')
    with pytest.raises(SpecError, match="format: expected 'likeness-material-fit'"):
        head_from_dict(_with_material({"fit": "other.json"}), tmp_path / "h.toml").skin_material()


def test_sample_head_names_a_fitted_real_silicone() -> None:
    mat = load_head(SAMPLE).skin_material()
    assert mat is not None and mat.model == "neo_hookean"
    assert "Ecoflex_00-50" in mat.source and mat.note  # the fit of a data/tensile file, and why it was chosen
