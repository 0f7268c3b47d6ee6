"""The loop's input trace and the show-control threads' realtime budget."""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from runtime.input_trace import POSTED, RECEIVED, TAKEN, WOKE, InputTrace
from runtime.rtbudget import RealtimeBudget


def test_trace_stamps_each_command_with_the_cycle_that_applied_it() -> None:
    tr = InputTrace(rows=4)
    tr.taken(1.0, 1.5)
    tr.taken(None, 1.6)
    tr.applied(2.0, 2.1)
    tr.taken(3.0, 3.2)
    rows = tr.last(3)
    assert rows[0].tolist() == [1.0, 1.5, 2.0, 2.1]
    assert np.isnan(rows[1, RECEIVED]) and rows[1, [TAKEN, WOKE, POSTED]].tolist() == [1.6, 2.0, 2.1]
    assert rows[2, TAKEN] == 3.2 and np.isnan(rows[2, WOKE])  # not applied yet
    for k in range(5):  # the ring wraps
        tr.taken(10.0 + k, 10.5 + k)
    tr.applied(20.0, 20.1)
    assert tr.count == 8 and tr.last(1)[0].tolist() == [14.0, 14.5, 20.0, 20.1]
    assert tr.last(10).shape == (4, 4)


def _policy() -> int:
    return os.sched_getscheduler(0)


def test_input_thread_keeps_realtime_within_its_budget_and_drops_it_when_spent() -> None:
    seen: dict[str, object] = {}

    def thread() -> None:
        p = RealtimeBudget(5, share=0.05, window_s=0.2)  # 10 ms of CPU per 200 ms window
        seen["enter"] = p.enter()
        seen["rt_at_start"] = p.realtime and _policy() == os.SCHED_FIFO
        p.spent()
        seen["rt_after_a_packet"] = p.realtime
        end = time.thread_time() + 0.02  # a flood's worth of work: 20 ms of CPU
        while time.thread_time() < end:
            pass
        p.spent()
        seen["rt_after_the_flood"] = p.realtime or _policy() == os.SCHED_FIFO
        seen["demoted"] = p.demoted
        time.sleep(0.25)  # a new window
        p.spent()
        seen["rt_in_a_new_window"] = p.realtime and _policy() == os.SCHED_FIFO
        p._set(False)

    th = threading.Thread(target=thread)
    th.start()
    th.join(10)
    if seen["enter"] != "SCHED_FIFO 5":  # no CAP_SYS_NICE here: the thread keeps normal scheduling
        assert seen["enter"] == "normal scheduling (SCHED_FIFO not permitted)" and not seen["rt_at_start"]
        return
    assert seen["rt_at_start"] and seen["rt_after_a_packet"]
    assert not seen["rt_after_the_flood"] and seen["demoted"] == 1
    assert seen["rt_in_a_new_window"]
    assert _policy() != os.SCHED_FIFO  # the test's own thread was never touched


def test_priority_zero_leaves_scheduling_alone() -> None:
    p = RealtimeBudget(0)
    assert p.enter() == "normal scheduling"
    p.spent()
    assert not p.realtime


def test_work_that_is_not_urgent_leaves_the_rest_of_the_budget_to_the_urgent_work() -> None:
    """A bus process's read after its write: realtime while less than half the budget is used, normal scheduling
    once more is (so the budget lasts for writes), realtime again for the next write."""
    seen: dict[str, object] = {}

    def thread() -> None:
        p = RealtimeBudget(5, share=0.1, window_s=0.5)  # 50 ms of CPU per 500 ms window
        seen["enter"] = p.enter()
        p.keep_for_urgent(0.5)
        seen["read_rt_early"] = p.realtime and _policy() == os.SCHED_FIFO
        end = time.thread_time() + 0.03  # 30 ms of reads and writes: more than half the budget
        while time.thread_time() < end:
            pass
        p.keep_for_urgent(0.5)
        seen["read_rt_late"] = p.realtime or _policy() == os.SCHED_FIFO
        p.rearm()  # the next write: within the budget, realtime again
        seen["write_rt"] = p.realtime and _policy() == os.SCHED_FIFO
        p._set(False)

    th = threading.Thread(target=thread)
    th.start()
    th.join(10)
    if seen["enter"] != "SCHED_FIFO 5":  # no CAP_SYS_NICE here
        return
    assert seen["read_rt_early"] and not seen["read_rt_late"] and seen["write_rt"]


_WHOLE_PROCESS = """
import json, os, threading, time
from runtime.rtbudget import RealtimeBudget
go, done = threading.Event(), threading.Event()
def helper():
    go.wait()
    end = time.thread_time() + 0.04  # 40 ms of CPU on another thread of the process
    while time.thread_time() < end:
        pass
    done.set()
    time.sleep(5)
th = threading.Thread(target=helper, daemon=True)
th.start()
p = RealtimeBudget(5, share=0.05, window_s=0.5, whole_process=True)  # 25 ms of the process's CPU per window
seen = {"enter": p.enter(), "helper_rt": os.sched_getscheduler(th.native_id) == os.SCHED_FIFO}
p.spent()
seen["rt_after_a_little"] = p.realtime
go.set()
done.wait(5)
p.spent()
seen["demoted"] = p.demoted
seen["helper_rt_after"] = os.sched_getscheduler(th.native_id) == os.SCHED_FIFO
seen["main_rt_after"] = os.sched_getscheduler(0) == os.SCHED_FIFO
print(json.dumps(seen))
"""


def test_a_whole_process_budget_schedules_every_thread_and_counts_their_cpu_together() -> None:
    """A bus process: its driver's receive thread is realtime with the write thread, and its CPU time spends the
    same budget (a helper thread's 40 ms of work demotes the whole process)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", _WHOLE_PROCESS], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    if seen["enter"] != "SCHED_FIFO 5":  # no CAP_SYS_NICE here: nothing to check
        return
    assert seen["helper_rt"] and seen["rt_after_a_little"]
    assert seen["demoted"] == 1 and not seen["helper_rt_after"] and not seen["main_rt_after"]
