"""Engines: a dead local worker loses no task, a poisonous task is isolated and reported, Dask runs the tasks."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from offline.engine import DaskEngine, LocalPoolEngine, SerialEngine


def write_square(out_dir: str, key: int, crash_once_dir: str | None = None, always_crash: bool = False,
                 raise_once_dir: str | None = None) -> str:
    """A task: writes key² to its own file and returns the path; may kill its worker or raise (test hooks)."""
    if always_crash:
        os._exit(7)
    if crash_once_dir is not None:
        marker = Path(crash_once_dir) / f"crash_{key}"
        if not marker.exists():
            marker.write_text("x")
            os._exit(9)
    if raise_once_dir is not None:
        marker = Path(raise_once_dir) / f"raise_{key}"
        if not marker.exists():
            marker.write_text("x")
            raise RuntimeError(f"transient failure of {key}")
    path = Path(out_dir) / f"r{key}.txt"
    path.write_text(str(key * key))
    return str(path)


def check_all(out, outcomes, keys):
    by_key = {o.key: o for o in outcomes}
    assert sorted(by_key) == sorted(keys)
    for k in keys:
        assert by_key[k].ok, by_key[k].error
        assert Path(by_key[k].result).read_text() == str(k * k)
    assert len(outcomes) == len(keys)


def test_local_pool_worker_crash_loses_no_task(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    keys = list(range(12))
    crash = {3, 8}
    with LocalPoolEngine(2) as eng:
        outs = list(eng.run(write_square, keys,
                            lambda k: (str(tmp_path), k, str(marks) if k in crash else None)))
        assert eng.rebuilds >= 1
    check_all(tmp_path, outs, keys)
    assert {o.key for o in outs if o.attempts > 1} >= crash


def test_local_pool_isolates_a_task_that_always_kills_its_worker(tmp_path):
    keys = list(range(6))
    with LocalPoolEngine(2, max_crashes=1) as eng:
        outs = {o.key: o for o in eng.run(write_square, keys, lambda k: (str(tmp_path), k, None, k == 2))}
    assert not outs[2].ok and "died" in outs[2].error
    for k in keys:
        if k != 2:
            assert outs[k].ok and Path(outs[k].result).read_text() == str(k * k)


def test_task_exceptions_are_retried_then_reported(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    outs = list(SerialEngine(retries=1).run(write_square, [1, 2], lambda k: (str(tmp_path), k, None, False,
                                                                               str(marks))))
    check_all(tmp_path, outs, [1, 2])
    assert all(o.attempts == 2 for o in outs)
    outs = list(SerialEngine(retries=0).run(write_square, [5], lambda k: (str(tmp_path / "nope"), k)))
    assert not outs[0].ok and "FileNotFoundError" in outs[0].error


def test_dask_local_cluster_runs_every_task_even_when_a_worker_dies(tmp_path):
    pytest.importorskip("dask.distributed")
    marks = tmp_path / "marks"
    marks.mkdir()
    keys = list(range(8))
    with DaskEngine(None, n_workers=2) as eng:
        assert eng.n_workers == 2
        outs = list(eng.run(write_square, keys, lambda k: (str(tmp_path), k, str(marks) if k == 5 else None),
                            max_in_flight=3))
    assert (marks / "crash_5").exists()  # the worker running task 5 died once; Dask rescheduled the task
    check_all(tmp_path, outs, keys)


def report_and_sleep(out_dir: str, key: int) -> str:
    """A task that records its worker's pid, then outlives any test (only its parent's death ends it early)."""
    import time

    (Path(out_dir) / f"pid_{key}").write_text(str(os.getpid()))
    time.sleep(120)
    return ""


POOL_PARENT = """
import sys
from offline.engine import LocalPoolEngine
from tests.offline.test_engine import report_and_sleep
with LocalPoolEngine(2) as eng:
    for _ in eng.run(report_and_sleep, [0, 1], lambda k: (sys.argv[1], k)):
        pass
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (dead, not yet reaped by init) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[-1][0] != "Z"
    except OSError:
        return True


def test_local_pool_workers_die_with_their_parent_killed_by_sigkill(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root))
    parent = subprocess.Popen([sys.executable, "-c", POOL_PARENT, str(tmp_path)], env=env, cwd=root)
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(pids) < 2 and time.monotonic() < deadline:
            pids = [int(p.read_text()) for p in tmp_path.glob("pid_*") if p.read_text()]
            time.sleep(0.05)
        assert len(pids) == 2, "workers did not start"
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 15.0  # the workers notice on their own schedule (a loaded host: seconds)
        while any(_alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [p for p in pids if _alive(p)], "workers outlived their parent"
    finally:
        parent.kill()
        parent.wait()
        for p in pids:
            if _alive(p):
                os.kill(p, signal.SIGKILL)
