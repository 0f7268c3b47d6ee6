"""The sample head's strain-guard report is reproduced from the FEM pose sets shipped packed beside it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from offline.dataset.pack import read_header

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample"
#: The FEM pose sets the report was made from, in the order the report names them (``docs/skin_guard.md``).
GUARD_PACKS = ("heads/sample/skin_guard_performances.npz", "heads/sample/skin_guard_random.npz")


def test_the_shipped_guard_report_is_reproduced_from_the_shipped_packs(tmp_path):
    """``likeness offline guard evaluate`` on the shipped packs gives the shipped report's agreement, errors and
    dataset hashes (the packs' content hashes), without any FEM."""
    shipped = json.loads((SAMPLE / "skin_guard_report.json").read_text())
    assert list(shipped["per_dataset"]) == list(GUARD_PACKS)
    out = tmp_path / "report.json"
    cmd = [sys.executable, "-m", "likeness.cli", "offline", "guard", "evaluate", "--config",
           "heads/sample/head.toml", "--dataset", *GUARD_PACKS, "--out", str(out), "--fresh", "0"]
    r = subprocess.run(cmd, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "TMPDIR": str(tmp_path)},
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr + r.stdout
    got = json.loads(out.read_text())
    assert not list(tmp_path.glob("likeness-guard-*"))  # the unpacked packs are removed
    for name in GUARD_PACKS:
        mine, theirs = got["per_dataset"][name], shipped["per_dataset"][name]
        assert mine["dataset_hash"] == theirs["dataset_hash"] == read_header(ROOT / name)["header"]["content_hash"]
        for key in ("poses", "guard_vs_fem", "reduced_vs_full", "check_vs_full", "guard_accepts_fem_refuses",
                    "guard_refuses_fem_accepts"):
            assert mine[key] == theirs[key], (name, key)
        for key in ("max_abs_error_vs_fem", "median_abs_error_vs_fem"):
            assert mine[key] == pytest.approx(theirs[key], rel=1e-6), (name, key)
    assert got["guard_vs_fem"] == shipped["guard_vs_fem"] and got["poses"] == shipped["poses"]
