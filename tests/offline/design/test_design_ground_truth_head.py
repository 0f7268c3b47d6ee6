"""The head ground-truth test at test size: the report has every figure the issue names, and the design moves
toward the truth (thickness and surfaces closer after than at the start)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from offline.design.ground_truth_head import HeadTruthSettings, run_head_ground_truth

ROOT = Path(__file__).resolve().parents[3]


@pytest.mark.slow
def test_quick_head_ground_truth_writes_its_report_and_moves_toward_the_truth(tmp_path: Path):
    r = run_head_ground_truth(ROOT / "heads" / "sample" / "head.toml", tmp_path, seed=1,
                              settings=HeadTruthSettings.quick())
    on_disk = json.loads((tmp_path / "report.json").read_text())
    for key in ("thickness_rel_error_max", "thickness_rel_error_mean", "before", "after", "actuation_error_max",
                "noise_m", "truth", "design"):
        assert key in on_disk
    assert r["truth"]["n_nodes"] > r["design"]["n_nodes"]  # the truth is simulated on a finer mesh
    assert r["after"]["surface_error_mean_m"] < r["before"]["surface_error_mean_m"]
    assert r["thickness_rel_error_mean"] < r["thickness_rel_error_start_mean"]
    assert (tmp_path / "thickness_recovery.png").stat().st_size > 10_000
