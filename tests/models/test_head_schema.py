"""Head files are checked against a typed schema: unknown tables and keys, wrong types, bad bytes are named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from models.errors import SpecError
from models.headspec import load_head
from models.jsonfile import load_json
from models.linkmap import LinkMap

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


def _head(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "head.toml"
    path.write_text(text)
    return path


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize(
    ("edit", "fragments"),
    [
        (lambda t: t + "\n[saftey]\nsafe_speed = 0.1\n", ["saftey", "unknown table", "safety"]),
        (lambda t: "mystery = 3\n" + t, ["mystery", "unknown table"]),
        (lambda t: t.replace('[head]\n', '[head]\nnmae = "x"\n'), ["head.nmae", "unknown key", "description"]),
        (lambda t: t.replace("[paths]\n", '[paths]\npredicter = "p.onnx"\n'), ["paths.predicter", "unknown key"]),
        (lambda t: t.replace("[skin]\n", "[skin]\nstrain_maxx = 0.3\n"),
         ["skin.strain_maxx", "unknown key", "strain_max"]),
        (lambda t: t.replace("min = -2.0", 'min = "low"', 1), ["actuators[0] (jaw).min", "expected float, got str"]),
        (lambda t: t.replace("simulated = true", "simulated = 1", 1), ["buses.can0.simulated", "expected bool"]),
        (lambda t: t + "\n[groups.g]\nkind = \"together\"\nactuators = [\"jaw\", \"blink\"]\nspeed = 2\n",
         ["groups.g.speed", "unknown key"]),
    ],
)
def test_unknown_tables_keys_and_wrong_types_name_file_and_key(tmp_path: Path, edit, fragments) -> None:
    path = _head(tmp_path, edit(SAMPLE.read_text()))
    with pytest.raises(SpecError) as info:
        load_head(path)
    text = _one_line(info)
    assert text.startswith(f"{path}: ")
    for frag in fragments:
        assert frag in text, text


def test_non_utf8_and_deeply_nested_head_files(tmp_path: Path) -> None:
    path = tmp_path / "head.toml"
    path.write_bytes(SAMPLE.read_bytes().replace(b"Likeness sample head", b"Likeness \xff sample head"))
    with pytest.raises(SpecError, match=r"head\.toml: byte \d+ \(line 8\): expected UTF-8 text.*0xff"):
        load_head(path)
    path.write_text("a = " + "[" * 5000 + "]" * 5000)
    with pytest.raises(SpecError, match="nested too deeply"):
        load_head(path)


def test_predictor_optional_is_a_boolean_of_paths(tmp_path: Path) -> None:
    text = SAMPLE.read_text().replace("[paths]\n", "[paths]\npredictor_optional = true\n")
    assert load_head(_head(tmp_path, text)).predictor_optional
    assert not load_head(SAMPLE).predictor_optional
    with pytest.raises(SpecError, match=r"paths\.predictor_optional"):
        load_head(_head(tmp_path, text.replace("predictor_optional = true", 'predictor_optional = "yes"')))


def test_binary_malformed_and_nested_link_maps_are_one_line_errors(tmp_path: Path) -> None:
    path = tmp_path / "linkmap.json"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(SpecError) as info:
        LinkMap.load(path)
    assert _one_line(info) == f"{path}: byte 0 (line 1): expected UTF-8 text for a link map, found byte 0x89"
    path.write_text('{"format": "likeness.linkmap",\n "links": [1, 2,]}')
    with pytest.raises(SpecError, match=r"linkmap\.json: line 2 column 17: not valid JSON for a link map"):
        LinkMap.load(path)
    path.write_text('{"a": ' + "[" * 2000 + "]" * 2000 + "}")
    with pytest.raises(SpecError, match=r"linkmap\.json: line 1 column 70: expected a link map nested at most 64"):
        LinkMap.load(path)


def test_brackets_inside_strings_do_not_count_as_nesting(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    doc = {"s": "[" * 500 + '\\"{', "a": [[1]]}
    path.write_text(json.dumps(doc))
    assert load_json(path) == doc
