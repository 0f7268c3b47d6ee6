"""CURVE allow-list, the example client speaking only docs/protocol.md, and the runtime's CLI commands."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from likeness.cli import main
from models.client import Client, DaemonTimeout, Telemetry
from tests._wait import wait_until
from tests.runtime.conftest import ROOT

PY = sys.executable


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_curve_allowed_key_served_unknown_key_gets_nothing(make_daemon, tmp_path: Path, capsys) -> None:
    keys, allow = tmp_path / "keys", tmp_path / "allowed"
    assert main(["keys", "daemon", "--out", str(keys)]) == 0
    assert main(["keys", "show", "--out", str(keys), "--allow", str(allow)]) == 0
    assert main(["keys", "stranger", "--out", str(keys)]) == 0
    assert main(["keys", "show", "--out", str(keys)]) == 2  # never overwrites a key
    assert (allow / "show.key").exists() and not (allow / "stranger.key").exists()
    d = make_daemon(api__curve_secret_key=str(keys / "daemon.key_secret"), api__curve_allow_dir=str(allow))
    server = keys / "daemon.key"
    with Client(d.command_endpoint, timeout=30, client_key=keys / "show.key_secret", server_key=server) as c, \
            Telemetry(d.telemetry_endpoint, client_key=keys / "show.key_secret", server_key=server) as tel:
        assert c.call("hello")["protocol"] == 1
        assert tel.recv(30.0) is not None  # telemetry flows to the allowed key
    with Client(d.command_endpoint, timeout=1, client_key=keys / "stranger.key_secret", server_key=server) as c, \
            Telemetry(d.telemetry_endpoint, client_key=keys / "stranger.key_secret", server_key=server) as tel:
        with pytest.raises(DaemonTimeout):
            c.call("hello")
        assert tel.recv(0.5) is None
    with Client(d.command_endpoint, timeout=1) as c, pytest.raises(DaemonTimeout):  # plain text: refused too
        c.call("hello")


def test_example_client_drives_the_head(make_daemon) -> None:
    d = make_daemon()
    out = subprocess.run([PY, str(ROOT / "examples" / "minimal_client.py"), d.command_endpoint],
                         capture_output=True, text=True, timeout=60, env=_env())
    assert out.returncode == 0, out.stderr
    assert "protocol 1, head 'sample', 13 actuators" in out.stdout
    assert "streamed 50 frames" in out.stdout
    assert d.lifecycle == "inactive"  # the client disabled the head at the end
    assert d.state.timeline.clips["nod"].duration == 1.0


def test_daemon_process_status_stream_estop_and_sigterm(tmp_path: Path) -> None:
    clip = tmp_path / "wave.csv"
    clip.write_text("time,jaw,blink\n0,0,0\n0.3,5,20\n0.6,0,0\n")
    proc = subprocess.Popen(
        [PY, "-m", "likeness", "daemon", "--command", "tcp://127.0.0.1:*", "--telemetry", "tcp://127.0.0.1:*",
         "--set", f'runtime.record_dir="{tmp_path}"'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=tmp_path)
    try:
        line = proc.stdout.readline()
        assert line.startswith("ready: head 'sample' (13 actuators)"), line + proc.stderr.read()
        endpoint = line.split("commands ")[1].split(",")[0]

        def cli(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run([PY, "-m", "likeness", *args, "--endpoint", endpoint], capture_output=True,
                                  text=True, timeout=60, env=_env())

        st = cli("status")
        assert st.returncode == 0 and "lifecycle inactive" in st.stdout, st.stderr
        sent = cli("stream", str(clip), "--enable", "--fps", "50")
        assert sent.returncode == 0, sent.stderr
        assert "streamed 31 frames of 'wave'" in sent.stdout
        up = cli("stream", str(clip), "--upload")
        assert up.returncode == 0 and "playing 'wave'" in up.stdout
        est = cli("estop", "--reason", "cli test")
        assert est.returncode == 0 and "e-stop latched" in est.stdout
        st = cli("status")
        assert "lifecycle estop" in st.stdout and "cli test" in st.stdout
        assert cli("enable").returncode == 5  # refused in the present state (latched), with a clear message
        assert cli("reset").returncode == 0
        with Client(endpoint) as c:
            assert c.call("status")["lifecycle"] == "inactive"
        proc.send_signal(signal.SIGUSR1)  # the e-stop signal
        with Client(endpoint) as c:
            assert wait_until(lambda: c.call("status")["lifecycle"] == "estop", 30)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        assert "daemon stopped" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_status_against_no_daemon_is_a_clear_error() -> None:
    out = subprocess.run([PY, "-m", "likeness", "status", "--endpoint", "tcp://127.0.0.1:9", "--timeout", "0.3"],
                         capture_output=True, text=True, timeout=60, env=_env())
    assert out.returncode == 4 and "no reply from tcp://127.0.0.1:9" in out.stderr  # 4: no daemon answered


def test_plot_command(tmp_path: Path, capsys) -> None:
    import numpy as np

    from runtime.recording import Recorder

    rec = Recorder(["jaw", "lid_l"], ["deg", "deg"], [np.pi / 180, np.pi / 180], capacity=100)
    for k in range(50):
        t = k * 0.01
        rec.add(t, np.radians([10 * t, 5.0]), np.radians([10 * t - 0.1, 5.0]))
    path = rec.save(tmp_path / "r.npz")
    assert main(["plot", str(path), "-o", str(tmp_path / "r.png")]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "r.png").read_bytes()[:4] == b"\x89PNG"
    assert "jaw" in out and "0.100 deg" in out
    assert main(["plot", str(tmp_path / "missing.npz")]) == 2
    time.sleep(0)
