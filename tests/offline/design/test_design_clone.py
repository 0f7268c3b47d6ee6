"""Face cloning: targets, the CLI's dry run and input errors, and (slow) a small run that resumes and writes a
skin asset the FEM pose problem loads unchanged."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from offline.design.clone import surface_distances
from offline.design.targets import DEFAULT_TARGETS, check_targets, load_targets

ROOT = Path(__file__).resolve().parents[3]
HEAD = ROOT / "heads" / "sample" / "head.toml"
UNITS = tuple(str(n) for n in np.load(ROOT / "heads" / "sample" / "skin" / "face_units.npz")["names"])


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "likeness.cli", "offline", "clone", *args], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=240)


def test_default_targets_are_expressive_and_valid():
    targets = check_targets(DEFAULT_TARGETS, UNITS, "default")
    assert len(targets) >= 8
    assert max(w.get("jawOpen", 0) for w in targets.values()) >= 0.9
    assert any("mouthSmileLeft" in w and "mouthSmileRight" not in w for w in targets.values())
    assert any("mouthSmileRight" in w and "mouthSmileLeft" not in w for w in targets.values())


def test_bad_targets_name_the_unit(tmp_path):
    f = tmp_path / "t.json"
    f.write_text(json.dumps({"grin": {"mouthSmileLeft": 0.5, "mouthSmileLeftt": 0.5}}))
    with pytest.raises(SpecError, match="mouthSmileLeftt"):
        load_targets(f, UNITS)
    f.write_text(json.dumps({"grin": {"mouthSmileLeft": "big"}}))
    with pytest.raises(SpecError, match="weight"):
        load_targets(f, UNITS)
    r = _cli("--config", str(HEAD), "--out", str(tmp_path / "o"), "--targets", str(f), "--dry-run")
    assert r.returncode != 0 and "grin" in r.stderr


def test_surface_distance_is_zero_on_the_surface_and_the_offset_off_it():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    F = np.array([[0, 1, 2], [1, 3, 2]])
    P = np.array([[0.25, 0.25, 0.0], [0.5, 0.5, 0.3], [2.0, 0.5, 0.0], [-1.0, -1.0, 0.0]])
    d = surface_distances(P, V, F)
    assert d == pytest.approx([0.0, 0.3, 1.0, np.sqrt(2)])


def test_dry_run_reports_problem_size_and_time():
    r = _cli("--config", str(HEAD), "--out", "/nonexistent/never-written", "--dry-run")
    assert r.returncode == 0, r.stderr
    assert "6472 tets" in r.stdout and "9 targets" in r.stdout and "estimated time" in r.stdout


@pytest.mark.slow
def test_small_clone_resumes_and_its_skin_is_a_head_asset(tmp_path):
    from offline.dataset.fem_problem import FemSpec
    from offline.design.clone import CloneRun, CloneSettings
    from offline.design.clone_report import write_report
    from offline.design.face import load_face

    face = load_face(HEAD)
    targets = {"lip_raise": {"mouthUpperUpLeft": 0.3, "mouthUpperUpRight": 0.3}}
    settings = CloneSettings(n_samples=8, max_outer=1, actuation_iterations=2, thickness_iterations=1)
    lines: list[str] = []
    state = CloneRun(face, targets, tmp_path, settings, progress=lines.append).run()
    assert any("ETA" in line for line in lines)
    assert (tmp_path / "checkpoint.npz").exists()
    again: list[str] = []
    state2 = CloneRun(face, targets, tmp_path, settings, progress=again.append).run()
    assert any("resuming" in line for line in again) and not any("actuation" in line for line in again)
    assert np.allclose(state2["h"], state["h"])
    run = CloneRun(face, targets, tmp_path, settings, progress=lambda s: None)
    report = write_report(run, state2, {"config": HEAD})
    row = report["targets"][0]
    assert row["after"]["surface_mean_m"] <= row["before"]["surface_mean_m"] + 1e-6
    assert (tmp_path / row["error_map"]).exists()
    skin = FemSpec(config=str(HEAD), mesh=str(tmp_path / "skin"),
                   linkmap=str(ROOT / "heads" / "sample" / "linkmap.json")).build()
    assert skin.mesh.n_tets == face.mesh.n_tets
    assert np.allclose(skin.base_surface(), face.skin.base_surface())  # outer surface kept
