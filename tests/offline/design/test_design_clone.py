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


def test_region_summary_judges_the_free_skin_of_targets_within_reach():
    from offline.design.clone_regions import region_summary

    def row(name, link_before, free_before, free_after):
        return {"name": name, "regions": {
            "jaw": {"n_vertices": 10, "before_mean_m": link_before, "after_mean_m": link_before},
            "free": {"n_vertices": 30, "before_mean_m": free_before, "after_mean_m": free_after}}}

    rows = [row("a", 0.5e-3, 2e-3, 1e-3), row("b", 1e-3, 1e-3, 1.01e-3), row("c", 9e-3, 4e-3, 1e-3)]
    sm = region_summary(rows, goal_mean_m=1.35e-3)
    assert sm["reachable_targets"] == ["a", "b"] and sm["out_of_reach_targets"] == ["c"]
    assert sm["free_region_before_mean_m"] == pytest.approx(1.5e-3)
    assert sm["free_region_reduction"] == pytest.approx(1 - 1.005e-3 / 1.5e-3)
    assert sm["worst_relative_change"] == pytest.approx(0.01)


def test_thickness_change_is_signed_along_the_thickness():
    from types import SimpleNamespace

    from offline.design.clone_regions import thickness_change
    from offline.design.warp import block_warp
    from offline.fem import box_mesh

    mesh = box_mesh((0.04, 0.02, 0.006), (8, 4, 2))
    warp = block_warp(mesh, n_samples=6)
    face = SimpleNamespace(inner=np.asarray(mesh.node_sets["z0"]),
                           locked=np.r_[mesh.node_sets["x0"], mesh.node_sets["x1"]])
    h = warp.h_ref.copy()
    h[0] += 0.001
    h[3] -= 0.0005
    dh, stats = thickness_change(warp, face, warp.h_ref, h)
    X = np.asarray(mesh.nodes)
    free = np.setdiff1d(face.inner, face.locked)
    assert np.allclose(dh, X[free, 2] - warp.rest_positions(h)[free, 2])  # thicker = bottom moved down
    assert stats["max_mm"] > 0 > stats["min_mm"] and stats["abs_max_mm"] <= 1.0 + 1e-9
