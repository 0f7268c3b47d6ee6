"""Config and asset errors reach the operator as one line, ``likeness COMMAND: error: FILE: KEY: ...``, exit 2."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from likeness.cli import main
from models.clip import ClipError, load_clip_file
from models.errors import SpecError
from models.headspec import load_head
from runtime.skin import SkinTargetSolver

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"


def _sample_copy(tmp_path: Path, edit=lambda t: t, name: str = "head.toml") -> Path:
    """The sample head in another folder: its relative predictor and link map paths point at missing files."""
    path = tmp_path / name
    path.write_text(edit(SAMPLE.read_text()))
    return path


def _one_error(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"likeness {command}: error: "), lines[0]
    return lines[0]


def test_misspelled_table_stops_the_daemon_at_start_up(tmp_path, capsys) -> None:
    path = _sample_copy(tmp_path, lambda t: t.replace("[safety]", "[saftey]"))
    assert main(["daemon", "--config", str(path)]) == 2
    line = _one_error(capsys, "daemon")
    assert f"{path}: saftey: unknown table" in line


def test_unknown_driver_lists_the_known_ones(tmp_path, capsys) -> None:
    path = _sample_copy(tmp_path, lambda t: t.replace('driver = "dynamixel"', 'driver = "dynamixl"'))
    assert main(["daemon", "--config", str(path)]) == 2
    line = _one_error(capsys, "daemon")
    assert "buses.dxl.driver: unknown driver; known: canopen402, dynamixel (got 'dynamixl')" in line


def test_missing_predictor_fails_at_start_up_naming_the_file(tmp_path, capsys) -> None:
    path = _sample_copy(tmp_path)
    assert main(["daemon", "--config", str(path)]) == 2
    line = _one_error(capsys, "daemon")
    assert f"paths.predictor: predictor file not found: {tmp_path / 'predictor.onnx'}" in line


def test_an_optional_predictor_may_be_missing(tmp_path, caplog) -> None:
    head = load_head(_sample_copy(tmp_path, lambda t: t.replace("[paths]\n", "[paths]\npredictor_optional = true\n")))
    assert SkinTargetSolver.from_head(head) is None
    assert "predictor.onnx not found" in caplog.text
    with pytest.raises(SpecError, match="predictor file not found"):
        SkinTargetSolver.from_head(load_head(_sample_copy(tmp_path, name="strict.toml")))


def test_module_entry_point_prints_the_error_without_traceback(tmp_path) -> None:
    path = _sample_copy(tmp_path, lambda t: t.replace("[safety]", "[saftey]"))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "likeness.cli", "daemon", "--config", str(path)],
                         capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 2
    assert res.stderr.startswith("likeness daemon: error: ") and "Traceback" not in res.stderr, res.stderr


def test_non_utf8_and_deeply_nested_clip_files(tmp_path, capsys) -> None:
    clip = tmp_path / "clip.json"
    clip.write_bytes(b'{"name": "x",\n "channels": {"jaw": \xc3\x28}}')
    with pytest.raises(ClipError, match=r"clip\.json: byte 35 \(line 2\): expected UTF-8 text for a clip"):
        load_clip_file(clip)
    assert main(["stream", str(clip)]) == 2
    assert "byte 35" in _one_error(capsys, "stream")
    clip.write_text('{"name": "x", "channels": ' + "[" * 1000 + "]" * 1000 + "}")
    with pytest.raises(ClipError, match=r"clip\.json: line 1 column 90: expected a clip nested at most 64"):
        load_clip_file(clip)
    csv = tmp_path / "clip.csv"
    csv.write_bytes(b"time,jaw\n0,1\n1,\xff\n")
    with pytest.raises(ClipError, match=r"clip\.csv: byte 15 \(line 3\)"):
        load_clip_file(csv)
