"""Suite-wide test setup: tests marked ``exclusive`` have the machine to themselves when pytest-xdist runs the suite.

The default test command runs isolated tests on two xdist workers (``-n 2 --dist loadgroup``, pyproject's
``addopts``). Tests that cannot share the machine (realtime loop timing, emulated buses with tight timeouts, daemons
and their emulator processes, the browser) are marked ``exclusive``: they all go to one worker (xdist group
``exclusive``, in collection order, so module fixtures are made once) and each runs under an exclusive lock that the
other worker's tests take shared, so nothing else runs beside them. A turnstile lock keeps a waiting exclusive test
from being starved by the shared ones. Without xdist (``-p no:xdist`` or ``-n 0``) nothing is locked.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

EXCLUSIVE = "exclusive"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Put every exclusive test in the one xdist group that a single worker runs."""
    for item in items:
        if item.get_closest_marker(EXCLUSIVE) is not None:
            item.add_marker(pytest.mark.xdist_group(EXCLUSIVE))


@contextmanager
def _flock(path: Path, mode: int) -> Iterator[None]:
    with path.open("a") as f:
        fcntl.flock(f, mode)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@contextmanager
def machine_share(exclusive: bool, run_id: str) -> Iterator[None]:
    """Hold the machine for one test: alone (``exclusive``) or shared with the other workers' shared tests."""
    base = Path(tempfile.gettempdir()) / f"likeness-pytest-{run_id}"
    turnstile, machine = base.with_suffix(".turnstile"), base.with_suffix(".machine")
    if exclusive:
        with _flock(turnstile, fcntl.LOCK_EX), _flock(machine, fcntl.LOCK_EX):
            yield
        return
    with _flock(turnstile, fcntl.LOCK_EX):  # wait behind an exclusive test that is waiting for the machine
        pass
    with _flock(machine, fcntl.LOCK_SH):
        yield


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Run the test (its setup, call and teardown, module fixtures included) under its share of the machine; the
    outermost wrapper, so that waiting for the machine does not count towards the test's timeout."""
    run_id = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run_id is None:
        yield
        return
    with machine_share(item.get_closest_marker(EXCLUSIVE) is not None, run_id):
        yield
