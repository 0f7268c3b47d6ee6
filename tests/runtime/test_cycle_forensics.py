"""A missed deadline's record names what held the loop thread: its own work, off its CPU, or another thread."""

from __future__ import annotations

import threading
import time

import pytest

from runtime.cycle_forensics import CycleForensics, classify

PERIOD = 0.002


def _spin_cpu(seconds: float) -> None:
    """Run on this thread until it has used ``seconds`` of CPU time."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def _cycle(f: CycleForensics, t: float, work, missed: int = 1):
    """One cycle: wake (no miss), do ``work``, end it, then wake again with ``missed``; the record made."""
    f.woke(t, 0.0, 0)
    work()
    f.work_done()
    f.woke(t + PERIOD, 1.5 * PERIOD, missed)
    return f.pending[-1] if missed else None


def test_a_cycle_that_computes_past_its_period_is_slow_work():
    f = CycleForensics(PERIOD)
    rec = _cycle(f, 1.0, lambda: _spin_cpu(3 * PERIOD))
    assert rec.cause == "work_slow"
    assert rec.work_s > PERIOD and rec.work_cpu_s >= 3 * PERIOD * 0.99
    assert rec.missed == 1 and rec.t == pytest.approx(1.0 + PERIOD)


def test_a_cycle_that_waits_past_its_period_is_work_off_its_cpu():
    f = CycleForensics(PERIOD)
    rec = _cycle(f, 1.0, lambda: time.sleep(4 * PERIOD))
    assert rec.cause == "work_off_cpu"
    assert rec.voluntary >= 1 and rec.work_cpu_s < 0.5 * rec.work_s


def test_another_thread_running_in_the_interval_is_named_the_interpreter_lock():
    period = 0.5  # long: the test's own thread taken off its CPU between two calls must not read as slow work
    f = CycleForensics(period)
    f.woke(1.0, 0.0, 0)
    f.work_done()
    th = threading.Thread(target=_spin_cpu, args=(0.02,))
    th.start()
    th.join()
    f.woke(1.0 + period, 1.5 * period, 1)
    rec = f.pending[-1]
    assert rec.others_cpu_s >= 0.019
    assert rec.cause == "interpreter_lock"


def test_commands_between_cycles_count_when_they_held_the_thread():
    period = 0.5  # long: the test's own thread taken off its CPU between two calls must not read as slow work
    f = CycleForensics(period)
    f.woke(1.0, 0.0, 0)
    f.work_done()
    f.between(0.8 * period)
    f.woke(1.0 + period, 1.5 * period, 2)
    assert f.pending[-1].cause == "between_cycles" and f.pending[-1].between_s == pytest.approx(0.8 * period)


def test_no_record_without_a_miss_and_take_empties_in_milliseconds():
    f = CycleForensics(PERIOD)
    assert _cycle(f, 1.0, lambda: None, missed=0) is None
    assert f.take() == [] and f.kept == 0
    _cycle(f, 2.0, lambda: _spin_cpu(3 * PERIOD))
    out = f.take()
    assert len(out) == 1 and f.pending == [] and f.kept == 1
    assert out[0]["cause"] == "work_slow" and out[0]["work_ms"] >= 3 * PERIOD * 1e3 * 0.99
    assert "work_s" not in out[0] and out[0]["t"] == pytest.approx(2.0 + PERIOD)


def test_the_first_wake_up_has_nothing_to_compare_with():
    f = CycleForensics(PERIOD)
    f.woke(1.0, 1.5 * PERIOD, 1)
    assert f.pending == []


@pytest.mark.parametrize(("args", "cause"), [
    ((0.003, 0.0029, 0.0, 0.0, 0, 0), "work_slow"),
    ((0.003, 0.0005, 0.0, 0.0, 1, 0), "work_off_cpu"),
    ((0.001, 0.001, 0.0015, 0.0, 0, 0), "between_cycles"),
    ((0.001, 0.001, 0.0, 0.0, 0, 2), "page_faults"),
    ((0.001, 0.001, 0.0, 0.001, 3, 0), "interpreter_lock"),
    ((0.001, 0.001, 0.0, 0.0, 3, 0), "preempted"),
    ((0.001, 0.001, 0.0, 0.0, 0, 0), "not_scheduled"),
])
def test_the_cause_is_the_first_evidence_that_fits(args, cause):
    assert classify(PERIOD, *args) == cause
