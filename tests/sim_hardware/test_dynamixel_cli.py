"""``likeness sim dynamixel`` as a subprocess, driven by a plain dynamixel-sdk client."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

ROOT = Path(__file__).resolve().parents[2]
READY = re.compile(r"^ready: (\d+) (\S+) servos \(ids ([\d,-]+)\) on (\S+) -> (\S+)(?:, control (\S+))?$")


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    """Widen the SDK's answer window (2 × latency timer + 2 ms) so a loaded test machine does not flake."""
    import dynamixel_sdk.port_handler

    monkeypatch.setattr(dynamixel_sdk.port_handler, "LATENCY_TIMER", 50)


def start(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "likeness", "sim", "dynamixel", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def ready_line(proc: subprocess.Popen, timeout: float = 20.0) -> re.Match:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    assert ready, "no ready line"
    line = proc.stdout.readline().strip()
    match = READY.match(line)
    assert match, f"unexpected ready line {line!r}; stderr: {proc.stderr.read() if proc.poll() is not None else ''}"
    return match


def _ping(ph: PacketHandler, port: PortHandler, dxl_id: int, tries: int = 3) -> tuple[int, int, int]:
    """Ping as a bus master does: the SDK's reply timeout is a few tens of milliseconds, which a busy host's
    scheduler can exceed, so a timed-out ping is sent again (any other answer is returned at once)."""
    for _ in range(tries - 1):
        answer = ph.ping(port, dxl_id)
        if answer[1] != COMM_RX_TIMEOUT:
            return answer
    return ph.ping(port, dxl_id)


def test_serve_sdk_client_and_sigterm(tmp_path: Path) -> None:
    link = tmp_path / "dxl"
    proc = start("--ids", "1-13", "--model", "XM430-W350", "--link", str(link), "--control", "tcp://127.0.0.1:0")
    try:
        match = ready_line(proc)
        assert match.group(1) == "13" and match.group(2) == "XM430-W350" and match.group(4) == str(link)
        assert os.path.realpath(link) == match.group(5)
        control = match.group(6)
        ids = list(range(1, 14))
        port = PortHandler(str(link))
        assert port.openPort() and port.setBaudRate(1_000_000)
        ph = PacketHandler(2.0)
        try:
            for i in ids:
                assert _ping(ph, port, i) == (1020, COMM_SUCCESS, 0)
            goals = {i: 100 + 37 * i for i in ids}
            writer = GroupSyncWrite(port, ph, 116, 4)
            for i in ids:
                writer.addParam(i, list(goals[i].to_bytes(4, "little")))
            assert writer.txPacket() == COMM_SUCCESS
            torque = GroupSyncWrite(port, ph, 64, 1)
            for i in ids:
                torque.addParam(i, [1])
            assert torque.txPacket() == COMM_SUCCESS
            reader = GroupSyncRead(port, ph, 132, 4)
            for i in ids:
                reader.addParam(i)
            seen: list[dict[int, int]] = []
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                if reader.txRxPacket() == COMM_SUCCESS:
                    seen.append({i: reader.getData(i, 132, 4) for i in ids})
                    if seen[-1] == goals:
                        break
                time.sleep(0.01)
            assert seen and seen[-1] == goals
            assert seen[0] != goals  # they moved there over time, not instantly
            # fault injection over the control channel shows up on the bus
            from models.emulator_control import request

            assert request(control, {"op": "inject", "fault": "overload", "device": 7})["ok"]
            assert ph.read1ByteTxRx(port, 7, 70) == (0x20, COMM_SUCCESS, 0x80)
            assert request(control, {"op": "clear"})["ok"]
        finally:
            port.closePort()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        assert not link.exists() and not link.is_symlink()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sigint_exits_cleanly(tmp_path: Path) -> None:
    link = tmp_path / "x"
    proc = start("--ids", "3,5", "--link", str(link))
    try:
        match = ready_line(proc)
        assert match.group(1) == "2" and match.group(3) == "3,5"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
        assert not link.is_symlink()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(("args", "message"), [
    (["--ids", "5-1"], "--ids: bad id range"),
    (["--model", "AX-12"], "--model: unknown model 'AX-12'"),
])
def test_bad_arguments_exit_2(tmp_path: Path, args: list[str], message: str) -> None:
    proc = start(*args, "--link", str(tmp_path / "y"))
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 2
    assert message in err


def test_refuses_to_replace_a_regular_file(tmp_path: Path) -> None:
    target = tmp_path / "file"
    target.write_text("keep me")
    proc = start("--link", str(target))
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 2 and "not a symlink" in err
    assert target.read_text() == "keep me"
