"""Suite-wide test setup: tests marked ``exclusive`` have the machine to themselves when pytest-xdist runs the suite.

The default test command runs the suite on two xdist workers, a test module at a time on one worker (``-n 2
--dist loadfile``, pyproject's ``addopts``: module fixtures such as a daemon or the browser are made once). Tests that
cannot share the machine (realtime loop timing, emulated buses with tight timeouts, daemons and their emulator
processes, fixed ports, the browser) are marked ``exclusive``: each runs under an exclusive lock that the other
worker's tests take shared, so nothing of the suite runs beside it. A turnstile lock keeps a waiting exclusive test
from being starved by the shared ones. Without xdist (``-p no:xdist`` or ``-n 0``) nothing is locked.
(xdist's ``loadgroup`` would keep the exclusive tests on one worker, but it marks groups by rewriting node ids, which
pytest 9 no longer reads.)
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
#: Modules whose every test is exclusive (a test elsewhere can say so with ``@pytest.mark.exclusive``): emulated
#: buses with tight timeouts, daemons with their emulators, timing and realtime-priority checks, fixed ports, the
#: browser.
EXCLUSIVE_MODULES = frozenset({
    "calibration/test_calib_cli.py", "calibration/test_calib_daemon.py", "calibration/test_calib_hardware.py",
    "drivers/test_canopen402.py", "drivers/test_dynamixel.py",
    "runtime/inputs/test_examples.py", "runtime/inputs/test_inputs_e2e.py", "runtime/inputs/test_sacn_multicast.py",
    "runtime/test_api_server.py", "runtime/test_bus_reconnect.py", "runtime/test_buslink.py",
    "runtime/test_daemon_e2e.py", "runtime/test_demo.py", "runtime/test_feedback_watch.py", "runtime/test_fuzz.py",
    "runtime/test_heartbeat_loss.py",
    "runtime/test_link_telemetry.py", "runtime/test_protocol_fuzz.py", "runtime/test_recording_cli.py",
    "runtime/test_security_cli.py", "runtime/test_skin_channels.py",
    "sim_hardware/test_canopen_emulator.py", "sim_hardware/test_canopen_socketcand.py",
    "sim_hardware/test_dynamixel_cli.py", "sim_hardware/test_dynamixel_emulator.py",
    "studio/test_browser.py",
})
TESTS = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the exclusive modules' tests."""
    for item in items:
        if item.path.is_relative_to(TESTS) and item.path.relative_to(TESTS).as_posix() in EXCLUSIVE_MODULES:
            item.add_marker(EXCLUSIVE)


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


#: The shipped heads: no test may change them (a test works on a copy; one that wrote through a link to a shipped
#: file once replaced the sample predictor with garbage, and every later test read it).
SHIPPED = Path(__file__).resolve().parents[1] / "heads"


def _shipped_files() -> dict[str, tuple[int, int]]:
    """Size and modification time of every shipped head file."""
    out = {}
    for p in SHIPPED.rglob("*"):
        if p.is_file():
            st = p.stat()
            out[str(p.relative_to(SHIPPED.parent))] = (st.st_size, st.st_mtime_ns)
    return out


def pytest_sessionstart(session: pytest.Session) -> None:
    session.config.stash[_SHIPPED_KEY] = _shipped_files()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Fail the run, naming the files, when a test changed, added or removed a shipped head's file."""
    before = session.config.stash.get(_SHIPPED_KEY, None)
    if before is None:
        return
    after = _shipped_files()
    changed = sorted(p for p in set(before) | set(after) if before.get(p) != after.get(p))
    if changed:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line("")
            reporter.write_line(f"the test run changed shipped head files (restore them from git): "
                                f"{', '.join(changed)}", red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


_SHIPPED_KEY = pytest.StashKey[dict[str, tuple[int, int]]]()
