"""The show-control examples run as written against a simulated daemon started with their own configs
(``examples/show_control/*.toml``; only the ports are moved to free ones): the head moves by OSC, by sACN and under
timecode."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest

from models.client import Client, Telemetry
from tests._wait import wait_until
from tests.runtime.conftest import ROOT, daemon_overrides
from tests.runtime.inputs.conftest import Events, enable, loopback_address, show_head, started

EXAMPLES = ROOT / "examples" / "show_control"


def _fragment(sacn_ip: str) -> str:
    """The three example configs in one fragment, on free ports."""
    text = "\n".join((EXAMPLES / name).read_text() for name in ("cue_osc.toml", "console_sacn.toml",
                                                                   "timecode.toml"))
    text = re.sub(r'bind = "127\.0\.0\.1:\d+"', 'bind = "127.0.0.1:0"', text)
    return text.replace('bind = "127.0.0.1"', f'bind = "{sacn_ip}"')


@pytest.fixture(scope="module")
def example_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    from models.headspec import load_head
    from runtime.daemon import Daemon

    tmp = tmp_path_factory.mktemp("examples")
    head = show_head(tmp, _fragment(loopback_address()))
    overrides = daemon_overrides(tmp, **{"safety.watchdog_hold_s": 1.0, "safety.watchdog_neutral_s": 3.0,
                                             "safety.feedback_timeout_s": 5.0})
    # target_solvers None: the head's skin solver, whose arkit.* channels the OSC example maps
    daemon = started(lambda: Daemon(load_head(head), overrides, target_solvers=None))
    try:
        yield daemon
    finally:
        daemon.stop()


def _run(script: str, *args: str, timeout: float = 120.0) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return done.stdout


def _peak(tel: Telemetry, name: str, seconds: float) -> float:
    """The largest commanded value of ``name`` in ``seconds`` of telemetry."""
    peak = -1e9
    for topic, msg in tel.iter(seconds):
        if topic == "state":
            peak = max(peak, msg["commanded"][name])
    return peak


def test_osc_cue_system_example_moves_the_head(example_daemon) -> None:
    import threading

    d = example_daemon
    with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint, topics=(b"state",)) as tel:
        port = c.call("hello")["inputs"]["osc"]["udp"].rsplit(":", 1)[1]
        out: list[str] = []
        th = threading.Thread(target=lambda: out.append(_run("osc_cue_system.py", "--port", port, "--wait", "8")))
        th.start()
        peak = _peak(tel, "jaw", 14.0)  # the cue: the jaw opens to 10 degrees and closes
        th.join(120.0)
        assert out and "cue sent" in out[0]
        assert peak > 5.0
        assert wait_until(lambda: c.call("status")["lifecycle"] == "inactive", 30)  # the cue system disabled it


def test_sacn_console_example_moves_the_head_then_the_watchdog_takes_over(example_daemon) -> None:
    import threading

    d = example_daemon
    with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint, topics=(b"state",)) as tel:
        dest = c.call("hello")["inputs"]["sacn"]["bind"].rsplit(":", 1)[0]
        enable(c)
        events = Events(d.telemetry_endpoint)
        try:
            th = threading.Thread(target=_run, args=("sacn_console.py", "--dest", dest, "--seconds", "4"))
            th.start()
            peak = _peak(tel, "jaw", 5.0)  # the console opens the jaw to 12 degrees
            th.join(120.0)
            assert peak > 6.0
            assert wait_until(lambda: events.of("watchdog", stage="neutral", source="sacn"), 30)
        finally:
            events.close()
        c.call("disable")


def test_mtc_show_example_chases_the_performance(example_daemon) -> None:
    d = example_daemon
    with Client(d.command_endpoint, timeout=30) as c:
        mtc = c.call("hello")["inputs"]["timecode"]["bind"]
        events = Events(d.telemetry_endpoint)
        try:
            out = _run("mtc_show.py", "--command", d.command_endpoint, "--mtc", mtc, "--roll", "3")
        finally:
            events.close()
        lines = dict(line.strip().split(": ", 1) for line in out.splitlines() if ": " in line)
        # what the daemon said meanwhile, for a failure's message (a fault or a stop would explain a lost source)
        said = out + "\n" + "\n".join(str(e) for e in events.items if e["event"] != "timecode" or e["change"] != "jump")
        # (the lock state is not asserted on each line: a loaded host can stall the generator into a dropout)
        assert "source timecode, clip expressive" in lines["rolling"], said
        assert "(hold, 25 fps)" in lines["held"], said
        assert "source timecode, clip expressive" in lines["relocated"], said
        assert re.search(r"timecode 01:00:(0[5-9]|1\d):", lines["relocated"]), said
        changes = iter([e["change"] for e in events.items if e["event"] == "timecode"])
        # in this order (a loaded host may add jumps between them)
        assert all(any(c == want for c in changes) for want in ("lock", "freewheel", "hold", "lock")), events.items
        c.call("disable")
