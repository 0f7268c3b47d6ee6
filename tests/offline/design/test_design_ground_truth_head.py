"""The head ground-truth test at test size with the model exact (truth on the design's own mesh, no noise): the
report has every figure the issue names, and the design moves toward the truth (thickness and surfaces much closer
after than at the start). With 0.05 mm noise or a finer truth mesh the thickness is not recovered on this head
(docs/design.md, "Ground truth on the head"): that is measured by the command, not asserted here."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from offline.design.ground_truth_head import quick_settings, run_head_ground_truth

ROOT = Path(__file__).resolve().parents[3]


@pytest.mark.slow
def test_quick_head_ground_truth_with_the_exact_model_moves_toward_the_truth(tmp_path: Path):
    r = run_head_ground_truth(ROOT / "heads" / "sample" / "head.toml", tmp_path, seed=1,
                              settings=quick_settings(truth_layers=2, noise_m=0.0))
    on_disk = json.loads((tmp_path / "report.json").read_text())
    for key in ("thickness_rel_error_max", "thickness_rel_error_mean", "before", "after", "actuation_error_max",
                "noise_m", "truth", "design"):
        assert key in on_disk
    assert r["truth"]["n_nodes"] == r["design"]["n_nodes"]
    assert r["after"]["surface_error_mean_m"] < 0.5 * r["before"]["surface_error_mean_m"]
    assert r["thickness_rel_error_mean"] < 0.5 * r["thickness_rel_error_start_mean"]
    assert r["identifiability"]["noise_for_10pct_max_m"] > 0
    assert (tmp_path / "thickness_recovery.png").stat().st_size > 10_000
