"""The soak benchmark's machinery: its accounting of missed deadlines and recorded rows (fast), and a short soak with
two faults against a real daemon on the emulated head (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import _soak_report as SR

ROOT = Path(__file__).resolve().parents[2]


def test_missed_deadlines_are_split_by_fault_handling_windows() -> None:
    # (t, cycles, missed, lifecycle, jaw commanded, jaw measured, feedback age)
    states = [(t, 0, m, "active", 0.0, 0.0, 0.0) for t, m in [(0.0, 0), (1.0, 0), (2.0, 3), (3.0, 3), (4.0, 5),
                                                                (5.0, 5), (6.0, 6)]]
    out = SR._missed(states, [(3.5, 4.5)], 0.5, 10.0)
    assert out == {"outside_fault_handling": 4, "during_fault_handling": 2}
    assert SR._missed(states, [], 2.5, 10.0)["outside_fault_handling"] == 3  # only increments inside the span


def test_recording_rows_count_the_cycles_absent_from_the_file(tmp_path: Path) -> None:
    period = 0.002
    t = np.concatenate([np.arange(0, 100) * period, (np.arange(103, 200)) * period])  # 3 cycles not run
    rows = np.column_stack([t, np.zeros((len(t), 2))])
    header = json.dumps({"format": "likeness.recording", "version": 1, "names": ["jaw"], "columns": 3})
    path = tmp_path / "r.lrec"
    path.write_bytes((header + "\n").encode() + rows.astype("<f8").tobytes() + b"\x00" * 5)  # a cut last record
    assert SR.recording_rows(str(path), period) == {"rows": 197, "absent_cycles": 3}
    assert SR.recording_rows(str(tmp_path / "missing.lrec"), period) == {"rows": 0, "absent_cycles": 0}
    # cycles run early on an input serve their slot ahead of its deadline: uneven steps, no cycle absent
    early = np.arange(0, 200) * period
    early[10::7] -= 0.75 * period
    early[12::9] -= 0.2 * period
    path.write_bytes((header + "\n").encode() + np.column_stack([early, np.zeros((200, 2))]).astype("<f8").tobytes())
    assert SR.recording_rows(str(path), period) == {"rows": 200, "absent_cycles": 0}


@pytest.mark.slow
def test_a_short_soak_detects_and_recovers_its_faults(tmp_path: Path) -> None:
    """30 s at 500 Hz: a drive's heartbeat stopped, then a malformed burst; both seen and recovered by the soak's
    operator, the recording complete, the report and the timeline written."""
    out = tmp_path / "soak"
    proc = subprocess.run([sys.executable, "benchmarks/soak.py", "--minutes", "0.5", "--interval", "10",
                           "--faults", "heartbeat_stopped,malformed_burst", "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=400)
    assert (out / "report.json").exists(), proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    faults = {f["fault"]: f for f in report["faults"]}
    assert set(faults) == {"heartbeat_stopped", "malformed_burst"}
    assert faults["heartbeat_stopped"]["detected"] and "0x8130" in faults["heartbeat_stopped"]["detected_by"]
    assert all(f["recovered"] for f in faults.values()), faults
    assert report["recording"]["rows_in_file"] > 5000 and report["recording"]["lost"] == 0
    assert report["settings"]["head_sha256"] and report["memory_mib"]["start"]["total"] > 0
    assert (out / "timeline.png").stat().st_size > 10_000
