"""``likeness offline clone --design-mechanism``: the dry run, a bad envelope, and (slow) a small run that writes
the report and the head folder and resumes from its checkpoint."""

from __future__ import annotations

import json

import numpy as np
import pytest

from likeness.cli import main
from tests.runtime.conftest import SAMPLE


def _small_layout(tmp_path, targets: dict, iterations: int) -> list[str]:
    """A layout design of the sample head small enough for a test: the jaw fixed, joints within 5 mm."""
    env = tmp_path / "env.toml"
    env.write_text("[envelope]\njoint_move_mm = 5\n[motors.jaw]\nfixed = true\n")
    return ["offline", "clone", "--config", str(SAMPLE), "--targets", _targets(tmp_path, targets),
            "--design-mechanism", "--design-iterations", str(iterations), "--envelope", str(env),
            "--out", str(tmp_path / "run")]


def _targets(tmp_path, targets: dict) -> str:
    path = tmp_path / "targets.json"
    path.write_text(json.dumps(targets))
    return str(path)


def test_the_dry_run_states_the_problem_and_stops(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    rc = main(["offline", "clone", "--config", str(SAMPLE), "--targets", _targets(tmp_path, {"blink": {
        "eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}}), "--design-mechanism", "--dry-run", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "layout design: 222 design variables in 100 groups" in text and "estimated time" in text
    assert "the attachments' own reach about" in text  # the bound stage is part of the estimate ...
    assert not out.exists()
    assert main(["offline", "clone", "--config", str(SAMPLE), "--targets", _targets(tmp_path, {"blink": {
        "eyeBlinkLeft": 1.0}}), "--design-mechanism", "--dry-run", "--no-attachment-bound", "--out", str(out)]) == 0
    assert "own reach" not in capsys.readouterr().out  # ... unless it is skipped


def test_a_bad_envelope_is_refused_naming_the_file_and_key(tmp_path, capsys) -> None:
    env = tmp_path / "env.toml"
    env.write_text("[envelope]\njoint_move_mm = -3\n")
    rc = main(["offline", "clone", "--config", str(SAMPLE), "--design-mechanism", "--dry-run", "--envelope", str(env),
               "--out", str(tmp_path / "run")])
    assert rc == 2
    assert f"{env}: envelope.joint_move_mm: must be a finite number >= 0" in capsys.readouterr().err


@pytest.mark.slow
def test_a_small_layout_design_writes_its_report_and_head_and_resumes(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    args = _small_layout(tmp_path, {"jaw_smile": {"jawOpen": 0.4, "mouthSmileLeft": 0.6}}, 2)
    assert main(args) == 0
    report = json.loads((out / "report.json").read_text())
    row = report["per_target"][0]
    assert row["after"]["surface_mean_m"] > 0 and "target_strain" in row
    assert report["inputs_sha256"]["envelope"] is not None
    assert all(p["item"] != "motors.jaw" for p in report["moved_parameters"])
    assert all(p.get("move", 0.0) <= 5.0 + 1e-9 for p in report["moved_parameters"])
    assert report["head_folder"]["file_vs_design_max_mm"] < 1e-3
    assert (out / "head" / "head.toml").is_file() and (out / "pictures" / "mechanism_after.png").is_file()
    # the attachments' own reach: every link freed, its figures beside the layout's
    assert report["summary"]["bound"]["links"] and row["bound"]["surface_mean_m"] > 0
    assert {c["link"] for c in row["bound_link_changes"]} == set(report["summary"]["bound"]["links"])
    assert "## The attachments' own reach" in (out / "report.md").read_text()
    capsys.readouterr()
    assert main(args) == 0  # again: resumed from the checkpoint, nothing recomputed but the report
    assert "resuming from" in capsys.readouterr().out
    again = json.loads((out / "report.json").read_text())
    assert again["per_target"][0]["after"] == row["after"]
    assert again["per_target"][0]["bound"] == row["bound"]  # the bound stage is checkpointed too


def test_ring_rounds_below_zero_are_refused(tmp_path, capsys) -> None:
    rc = main(["offline", "clone", "--config", str(SAMPLE), "--targets", _targets(tmp_path, {"blink": {
        "eyeBlinkLeft": 1.0}}), "--design-mechanism", "--dry-run", "--ring-rounds", "-1", "--out",
        str(tmp_path / "run")])
    assert rc == 2
    assert "--ring-rounds -1: must be >= 0" in capsys.readouterr().err


def test_thickness_design_needs_the_layout_design(tmp_path, capsys) -> None:
    targets = _targets(tmp_path, {"blink": {"eyeBlinkLeft": 1.0}})
    rc = main(["offline", "clone", "--config", str(SAMPLE), "--targets", targets, "--design-thickness", "--dry-run",
               "--out", str(tmp_path / "run")])
    assert rc == 2
    assert "--design-thickness: only with --design-mechanism" in capsys.readouterr().err


@pytest.mark.slow
def test_layout_then_thickness_installs_the_optimized_skin_in_the_head_folder(tmp_path, capsys) -> None:
    from offline.fem import load_mesh

    out = tmp_path / "run"
    args = [*_small_layout(tmp_path, {"smile": {"mouthSmileLeft": 0.6, "mouthSmileRight": 0.6}}, 1),
            "--ring-rounds", "0", "--design-thickness", "--max-outer", "1", "--samples", "8"]
    assert main([*args, "--dry-run"]) == 0
    assert "then thickness on the redesigned head" in capsys.readouterr().out  # the dry run estimates both stages
    assert main(args) == 0  # the mold of the new skin passes its checks too
    report = json.loads((out / "report.json").read_text())
    t = report["thickness"]
    assert t["after"]["surface_mean_m"] <= t["before"]["surface_mean_m"] * 1.001  # a worse step is not kept
    assert "## Thickness on the redesigned head" in (out / "report.md").read_text()
    # the head folder's skin is the clone's optimized skin, with its provenance ...
    assert (out / "head" / "skin" / "skin.vtu").read_bytes() == (out / "thickness" / "skin" / "skin.vtu").read_bytes()
    assert "clone" in json.loads((out / "head" / "skin" / "mesh_report.json").read_text())
    original = load_mesh(SAMPLE.parent / "skin" / "skin.vtu")
    designed = load_mesh(out / "head" / "skin" / "skin.vtu")
    assert designed.n_nodes == original.n_nodes
    moved = np.linalg.norm(np.asarray(designed.nodes) - np.asarray(original.nodes), axis=1)
    for name, nodes in original.node_sets.items():  # ... and its attachments are where they were
        assert np.array_equal(np.asarray(designed.node_sets[name]), np.asarray(nodes))
        assert moved[np.asarray(nodes)].max() < 1e-9, name
    assert (out / "mold" / "mold_report.json").is_file()
