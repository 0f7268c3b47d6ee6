"""The socketcand bridge and ``likeness sim canopen`` across processes, with canopen's BaseNode402 master."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import canopen
import pytest

from sim_hardware.socketcand import SocketcandServer, format_frame, parse_send
from tests._wait import wait_until
from tests.sim_hardware.canopen_master import setup_master

ROOT = Path(__file__).resolve().parents[2]
READY = re.compile(
    r"^ready: (\d+) CiA 402 drives \(nodes (\S+)\) on socketcand ([\d.]+):(\d+) channel can0, control (\S+)$"
)


def _recv(bus: can.BusABC, timeout: float = 10.0) -> can.Message | None:
    return bus.recv(timeout)


def test_frame_format_and_parse():
    msg = can.Message(arbitration_id=0x205, data=b"\x01\x02\x03\x04", is_extended_id=False, timestamp=12.5)
    assert format_frame(msg) == b"< frame 205 12.500000 01020304 >"
    empty = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=1.0)
    assert format_frame(empty) == b"< frame 080 1.000000  >"
    ext = parse_send("< send 1ABCDEF0 2 a b >")
    assert ext.is_extended_id and ext.arbitration_id == 0x1ABCDEF0 and bytes(ext.data) == b"\x0a\x0b"
    with pytest.raises(ValueError, match="length"):
        parse_send("< send 205 3 1 2 >")


def test_bridge_between_clients_and_bus():
    channel = f"test-scd-{uuid.uuid4().hex[:10]}"
    local = can.Bus(interface="virtual", channel=channel)
    with SocketcandServer(bus_kwargs={"interface": "virtual", "channel": channel}, port=0) as server:
        # Handshake seen by a raw client, and a wrong channel refused.
        with socket.create_connection(server.address, timeout=1) as raw:
            assert raw.recv(64) == b"< hi >"
            raw.sendall(b"< open vcan9 >")
            assert raw.recv(64).startswith(b"< error")
        a = can.Bus(interface="socketcand", host=server.host, port=server.port, channel="can0")
        b = can.Bus(interface="socketcand", host=server.host, port=server.port, channel="can0")
        try:
            # both clients in raw mode on the server (frames to them are forwarded, or held for the grace period)
            wait_until(lambda: server.client_count == 2 and all(c.raw for c in server._clients), 10,
                       "both clients in raw mode")
            a.send(can.Message(arbitration_id=0x123, data=b"\xde\xad", is_extended_id=False))
            got = _recv(local)
            assert got is not None and got.arbitration_id == 0x123 and bytes(got.data) == b"\xde\xad"
            got = _recv(b)
            assert got is not None and got.arbitration_id == 0x123 and bytes(got.data) == b"\xde\xad"
            assert _recv(a, 0.1) is None  # never echoed to the sender
            local.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
            for client in (a, b):
                got = _recv(client)
                assert got is not None and got.arbitration_id == 0x80 and len(got.data) == 0
            burst = [
                can.Message(arbitration_id=0x180 + i, data=bytes([i]) * 8, is_extended_id=False) for i in range(50)
            ]
            for msg in burst:
                local.send(msg)
            ids = []
            while len(ids) < 50 and (m := _recv(a)) is not None:
                ids.append(m.arbitration_id)
            assert ids == [0x180 + i for i in range(50)]  # order kept, nothing lost
            assert server.client_count == 2
        finally:
            a.shutdown()
            b.shutdown()
        assert wait_until(lambda: server.client_count == 0, 10)
    local.shutdown()


@pytest.fixture
def served(tmp_path):
    """``likeness sim canopen`` in a subprocess on a free port, with a control endpoint."""
    eds = tmp_path / "drive.eds"
    proc = subprocess.Popen(
        [sys.executable, "-m", "likeness", "sim", "canopen", "--nodes", "1-3", "--port", "0",
         "--heartbeat-ms", "20", "--control", "tcp://127.0.0.1:0", "--eds-out", str(eds)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = proc.stdout.readline().strip()
        match = READY.match(line)
        assert match, f"unexpected ready line {line!r}; stderr: {proc.stderr.read() if proc.poll() else ''}"
        yield proc, match, eds
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_cli_base_node_402_across_processes_inject_and_sigterm(served):
    proc, match, eds = served
    assert match.group(1) == "3" and match.group(2) == "1-3"
    assert eds.exists() and canopen.import_od(str(eds), 1)[0x6502].default & 0x80
    port, control = int(match.group(4)), match.group(5)
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.1
    net.connect(interface="socketcand", host="127.0.0.1", port=port, channel="can0", tcp_tune=True)
    try:
        node = setup_master(net, 2)
        net.sync.start(0.01)
        node.rpdo[1].start(0.01)
        node.nmt.state = "OPERATIONAL"
        node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
        start = time.monotonic()
        while (t := time.monotonic() - start) < 0.5:
            node.rpdo[1]["Target position"].raw = round(15_000 * min(t / 0.4, 1.0))
            time.sleep(0.01)
        assert wait_until(lambda: abs(node.tpdo[1]["Position actual value"].raw - 15_000) < 20, 10)

        emcy: list[int] = []
        node.emcy.add_callback(lambda e: emcy.append(e.code))
        out = subprocess.run(
            [sys.executable, "-m", "likeness", "sim", "inject", "--control", control, "drive_fault", "device=2",
             "code=0x2310"],
            cwd=ROOT, capture_output=True, text=True, timeout=30,
        )
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["ok"] is True
        assert wait_until(lambda: 0x2310 in emcy, 10)
        assert wait_until(lambda: node.state == "FAULT", 10)
        bad = subprocess.run(
            [sys.executable, "-m", "likeness", "sim", "inject", "--control", control, "drive_fault", "device=9"],
            cwd=ROOT, capture_output=True, text=True, timeout=30,
        )
        assert bad.returncode == 1 and "no emulated drive with node id 9" in bad.stderr
    finally:
        net.sync.stop()
        net.disconnect()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
    assert proc.stdout.read() == ""  # exactly one line on stdout


def test_cli_rejects_bad_nodes():
    out = subprocess.run(
        [sys.executable, "-m", "likeness", "sim", "canopen", "--nodes", "0-3", "--port", "0"],
        cwd=ROOT, capture_output=True, text=True, timeout=30,
    )
    assert out.returncode == 2 and "--nodes" in out.stderr


def test_cli_exits_cleanly_on_sigint():
    proc = subprocess.Popen(
        [sys.executable, "-m", "likeness", "sim", "canopen", "--nodes", "4", "--port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith("ready: 1 CiA 402 drives (nodes 4) on socketcand 127.0.0.1:")
        proc.send_signal(signal.SIGINT)
        assert proc.wait(10) == 0
        assert proc.stderr.read() == ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
