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


def test_the_daemons_misses_are_set_beside_the_machines_own_stalls() -> None:
    states = [(t, 0, m, "active", 0.0, 0.0, 0.0) for t, m in [(0.0, 0), (1.0, 0), (2.0, 3), (3.0, 3), (4.0, 5),
                                                                (5.0, 5), (6.0, 6)]]
    # the bare loop missed at 1.5 s (with the daemon's 3), at 4.0 s (inside a fault window) and at 5.9 s (with its 1)
    sentinel = {"scheduling": "SCHED_FIFO 80", "misses": [(1.5, 2, 0.0041), (4.0, 1, 0.0023), (5.9, 1, 0.0021)]}
    out = SR._machine_stalls(states, [(3.5, 4.5)], 0.5, 10.0, sentinel)
    expect = {"scheduling": "SCHED_FIFO 80", "missed_outside_fault_handling": 3, "worst_lateness_ms": 4.1,
              "slow_wakeups_outside_fault_handling": 0, "probe_median_us": [], "slow_factor": None,
              "daemon_misses_outside": 4, "daemon_misses_with_one": 4,
              "daemon_misses_with_a_miss_or_slow_wakeup": 4}
    assert {k: out[k] for k in expect} == expect
    assert out["matched_by"].startswith("state messages")
    alone = SR._machine_stalls(states, [(3.5, 4.5)], 0.5, 10.0, {"misses": [(5.9, 1, 0.0021)]})
    assert (alone["daemon_misses_outside"], alone["daemon_misses_with_one"]) == (4, 1)
    # slow wake-ups (the probe over its factor) at 1.98 s (beside the daemon's 3 of 1..2 s), 4.2 s (in a fault
    # window) and 8.0 s (no daemon miss near)
    slow = SR._machine_stalls(states, [(3.5, 4.5)], 0.5, 10.0, {"misses": [(5.9, 1, 0.0021)], "slow_factor": 3.0,
                                                                   "slow": [(1.98, 9e-5), (4.2, 8e-5), (8.0, 7e-5)],
                                                                   "probe_median": [2.1e-5, 2.2e-5]})
    assert slow["slow_wakeups_outside_fault_handling"] == 2 and slow["probe_median_us"] == [21.0, 22.0]
    assert (slow["daemon_misses_with_one"], slow["daemon_misses_with_a_miss_or_slow_wakeup"]) == (1, 4)


def test_the_daemons_misses_at_their_own_times_match_only_the_host_signs_beside_them() -> None:
    states = [(t, 0, m, "active", 0.0, 0.0, 0.0) for t, m in [(0.0, 0), (1.0, 0), (2.0, 3), (3.0, 3), (4.0, 5),
                                                                (5.0, 5), (6.0, 6)]]
    sentinel = {"misses": [(1.5, 2, 0.0041), (5.9, 1, 0.0021)], "slow": [(1.98, 9e-5)]}
    # the loop's own times: 3 at 1.2 s (no sign within 50 ms: the state span 1..2 s would have matched both),
    # 1 at 5.93 s (beside the bare loop's miss at 5.9 s)
    out = SR._machine_stalls(states, [(3.5, 4.5)], 0.5, 10.0, sentinel, records=[(1.2, 3), (5.93, 1)])
    assert out["matched_by"] == "the loop's own miss times"
    assert (out["daemon_misses_outside"], out["daemon_misses_with_one"],
            out["daemon_misses_with_a_miss_or_slow_wakeup"]) == (4, 1, 1)
    # three signs outside the fault window, each covering 0.1 s of the 9.5 - 1.0 s outside it
    assert out["chance_near_a_miss_or_slow_wakeup"] == pytest.approx(0.3 / 8.5, abs=2e-3)


def test_the_loops_own_account_of_its_misses_is_counted_per_cause_outside_fault_handling() -> None:
    def rec(t: float, cause: str, missed: int = 1, late_ms: float = 2.5) -> dict:
        return {"t": t, "cause": cause, "missed": missed, "late_ms": late_ms}

    events = [{"event": "deadline_miss", "t": 1.2, "causes": [rec(1.1, "work_slow", 2), rec(1.15, "preempted")]},
              {"event": "deadline_miss", "t": 4.1, "causes": [rec(4.0, "work_slow")]},  # inside the fault window
              {"event": "fault", "t": 4.0},
              {"event": "deadline_miss", "t": 6.0, "causes": [rec(5.9, "work_slow", 1, 7.0)]}]
    sentinel = {"misses": [(5.92, 1, 0.002)], "slow": [(1.16, 9e-5)]}
    out = SR._miss_causes(events, [(3.5, 4.5)], 0.5, 10.0, sentinel)
    assert out["by_cause"] == {"work_slow": {"missed": 3, "records": 2, "with_host_sign": 1},
                               "preempted": {"missed": 1, "records": 1, "with_host_sign": 1}}
    assert out["recorded_missed"] == 4 and out["worst_record_per_cause"]["work_slow"]["t"] == 5.9


def test_the_sentinel_counts_a_stall_of_its_own_process() -> None:
    """A bare loop stopped for 50 ms (SIGSTOP, as a hypervisor takes the CPU) misses about 25 deadlines at 500 Hz."""
    import os
    import signal
    import time

    from benchmarks._soak_sentinel import Sentinel

    s = Sentinel(500.0, 1, cpu=0).start()
    pid = s._procs[0][1].pid
    time.sleep(0.6)
    os.kill(pid, signal.SIGSTOP)
    time.sleep(0.05)
    os.kill(pid, signal.SIGCONT)
    time.sleep(0.3)
    misses = s.stop()
    assert sum(n for _, n, _ in misses) >= 20 and max(late for _, _, late in misses) >= 0.04, misses
    assert len(s.probe_median) == 1 and 0 < s.probe_median[0] < 1e-3  # calibrated over the first 250 wake-ups


def test_a_sentinels_probe_is_fixed_work() -> None:
    from benchmarks._soak_sentinel import _probe

    assert _probe() == _probe() and _probe(10) != _probe(200)


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
