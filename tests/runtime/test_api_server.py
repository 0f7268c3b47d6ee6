"""The API server process and the core behind it, on a daemon with no buses (fast, no emulators): replies, e-stop
preemption behind large requests, clip budget and unloading, telemetry."""

from __future__ import annotations

import time
from pathlib import Path

import msgpack
import pytest
import zmq

from models.client import Client, DaemonError, Telemetry
from models.headspec import load_head
from runtime.core.state import CoreState
from runtime.daemon import Daemon
from runtime.hardware import Hardware

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


@pytest.fixture(scope="module")
def busless(tmp_path_factory: pytest.TempPathFactory):
    head = load_head(SAMPLE)
    tmp = tmp_path_factory.mktemp("busless")
    d = Daemon(head, {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                      "runtime.record_dir": str(tmp), "runtime.rate_hz": 500.0,
                      "runtime.clip_memory_bytes": 8 << 20},
               hardware=Hardware(head, {}), target_solvers=())
    d.start()
    yield d
    d.stop()


def _big_clip(name: str, keys: int) -> dict:
    ts = [i * 0.001 for i in range(keys)]
    return {"name": name, "channels": {"jaw": {"interp": "linear", "keys": [[t, 5.0 * (i % 3)] for i, t in
                                                                           enumerate(ts)]}}}


def test_hello_lists_ops_and_budget(busless: Daemon) -> None:
    with Client(busless.command_endpoint, timeout=30) as c:
        h = c.call("hello")
    assert "unload_clip" in h["ops"] and h["clip_memory_bytes"] == 8 << 20
    assert h["head"]["channels"]["blink"] == "deg" and not any(k.startswith("arkit.") for k in h["head"]["channels"])


def test_estop_overtakes_a_large_request_being_decoded(busless: Daemon) -> None:
    ctx = zmq.Context.instance()
    big = ctx.socket(zmq.DEALER)
    big.setsockopt(zmq.LINGER, 0)
    big.connect(busless.command_endpoint)
    with Client(busless.command_endpoint, timeout=30) as c:
        if c.call("status")["lifecycle"] != "active":
            c.call("reset")
            c.call("enable")
        payload = msgpack.packb({"op": "load_clip", "id": 1, "clip": _big_clip("big", 30000)})
        assert len(payload) > 500_000
        big.send(payload)
        t0 = time.monotonic()
        reply = c.call("estop", reason="overtake")
        t_estop = time.monotonic() - t0
        assert reply["lifecycle"] == "estop"
        assert big.poll(10000)
        big_reply = msgpack.unpackb(big.recv())
        t_big = time.monotonic() - t0
        assert big_reply["ok"], big_reply
        assert t_estop < t_big  # the e-stop was not queued behind the large request
        assert c.call("status")["estop"] == "overtake"
        c.call("reset")
    big.close()


def test_clip_budget_and_unload(busless: Daemon) -> None:
    with Client(busless.command_endpoint, timeout=30) as c:
        names = []
        with pytest.raises(DaemonError) as info:
            for k in range(50):
                names.append(c.call("load_clip", clip=_big_clip(f"c{k}", 20000))["clip"])
        assert info.value.code == "too_large" and "budget" in info.value.message
        used = c.call("status")["clip_bytes"]
        assert 0 < used <= 8 << 20
        for name in names:
            c.call("unload_clip", clip=name)
        assert c.call("status")["clip_bytes"] < used
        assert not set(names) & set(c.call("status")["timeline"]["clips"])
        with pytest.raises(DaemonError) as info:
            c.call("unload_clip", clip=names[0])
        assert info.value.code == "not_found"


def test_replies_carry_the_request_id_and_telemetry_flows(busless: Daemon) -> None:
    with Client(busless.command_endpoint, timeout=30) as c, Telemetry(busless.telemetry_endpoint) as tel:
        if c.call("status")["lifecycle"] != "active":
            c.call("enable")
        assert c.request("pose", pose={"jaw": 3.0}, speed=1.0)["ok"]
        msg = tel.wait_for(lambda t, m: t == "state" and m["lifecycle"] == "active" and m["loop"], 30)
        assert msg is not None and msg[1]["loop"]["rate_hz"] == 500.0
        raw = c.send_raw(msgpack.packb({"op": "pose", "id": "abc", "pose": {"nose": 1.0}}))
        assert raw["id"] == "abc" and raw["error"]["code"] == "unknown_channel"


def test_multipart_and_oversize_requests_are_refused_without_echo(busless: Daemon) -> None:
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(busless.command_endpoint)
    try:
        junk = b"x" * 200_000
        sock.send_multipart([msgpack.packb({"op": "status", "id": 5}), junk, junk])
        assert sock.poll(5000)
        frames = sock.recv_multipart()
        assert len(frames) == 1 and len(frames[0]) < 1000  # one short reply, nothing echoed
        reply = msgpack.unpackb(frames[0])
        assert reply["error"]["code"] == "bad_request" and "frames" in reply["error"]["message"]
        big = msgpack.packb({"id": "big-1", "op": "stream", "channels": ["jaw"],
                             "frames": [[float(i), 1.0] for i in range(120_000)]})
        assert len(big) > busless.cfg.api.max_message_bytes
        sock.send(big)
        assert sock.poll(5000)
        reply = msgpack.unpackb(sock.recv())
        assert reply["error"]["code"] == "too_large" and reply["id"] == "big-1"
    finally:
        sock.close()


def test_remote_binding_needs_curve_or_an_explicit_insecure_flag() -> None:
    from models.errors import SpecError
    from runtime.config import daemon_config

    head = load_head(SAMPLE)
    remote = {"api.command": "tcp://0.0.0.0:5555", "api.allow_remote": True}
    with pytest.raises(SpecError, match="insecure_remote"):
        daemon_config(head, remote)
    assert daemon_config(head, {**remote, "api.insecure_remote": True}).api.insecure_remote


def test_a_recorded_run_replays_bit_for_bit(tmp_path) -> None:
    """Every cycle's inputs of a live daemon (commands taken between cycles included) replayed on a fresh core give
    the same commands, bit for bit."""
    from runtime.core import core as K

    head = load_head(SAMPLE)
    d = Daemon(head, {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                      "runtime.record_dir": str(tmp_path), "runtime.rate_hz": 500.0},
               hardware=Hardware(head, {}), target_solvers=(), record_inputs=True)
    d.start()
    try:
        with Client(d.command_endpoint, timeout=30) as c:
            c.call("enable")
            c.call("load_clip", clip=_big_clip("c", 300))
            c.call("play", clip="c")
            time.sleep(0.15)
            c.call("pose", pose={"jaw": 4.0, "blink": 12.0}, speed=1.0)
            time.sleep(0.1)
            t = c.call("clock")["t_send"]
            c.call("stream", channels=["brow_l"], frames=[[t + 0.01 * k, 2.0 * k] for k in range(10)])
            time.sleep(0.15)
            c.call("estop")
            c.call("reset")
    finally:
        d.stop()
    inputs, writes = d.input_log, d.runner.output_log
    assert inputs and len(inputs) == len(writes)
    assert any(i.between_cycles for i in inputs) and sum(w is not None for w in writes) > 100
    fresh = CoreState.initial(head, d.params, [])
    for k, inp in enumerate(inputs):
        out = K.step(fresh, d.params, inp)
        if writes[k] is None:
            assert out.write is None, k
        else:
            assert out.write is not None and out.write.tobytes() == writes[k].tobytes(), k


def test_api_priority_holds_every_thread_of_the_server_process_within_one_budget() -> None:
    """``runtime.api_priority``: the API server process, every thread (ZeroMQ's I/O thread, a thread started by an
    input before the server entered the budget, one started after and entering it itself), goes SCHED_FIFO within
    one budget; threads spending it concurrently demote the whole process together."""
    import json
    import subprocess
    import sys
    import textwrap

    from runtime.server import server_budget

    assert server_budget(0) is None
    code = textwrap.dedent("""
        import json, os, threading, time, zmq
        from runtime.server import server_budget
        budget = server_budget(3)
        ctx = zmq.Context(); sock = ctx.socket(zmq.PAIR); sock.bind("inproc://x")
        stop, go = threading.Event(), threading.Event()
        def early():  # an input's thread, started (and entering) before the server does
            budget.enter(); go.wait()
            end = time.thread_time() + 0.05
            while time.thread_time() < end:
                budget.spent()
            tasks = os.listdir("/proc/self/task")  # right away, in the window that ran out
            seen["any_fifo_after"] = any(os.sched_getscheduler(int(t)) == os.SCHED_FIFO for t in tasks)
            stop.wait()
        seen = {}
        a = threading.Thread(target=early); a.start()
        time.sleep(0.05)
        seen["enter"] = budget.enter()
        b = threading.Thread(target=lambda: (budget.enter(), go.wait(), budget.spent(), stop.wait())); b.start()
        time.sleep(0.05)
        fifo = {int(t): os.sched_getscheduler(int(t)) == os.SCHED_FIFO for t in os.listdir("/proc/self/task")}
        seen["all_fifo"] = all(fifo.values()) and len(fifo) >= 4
        go.set(); time.sleep(0.3)
        seen["demoted"] = budget.demoted
        stop.set(); a.join(); b.join()
        print(json.dumps(seen))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    seen = json.loads(out.strip().splitlines()[-1])
    if seen["enter"] != "SCHED_FIFO 3":
        pytest.skip("SCHED_FIFO not permitted here")
    assert seen["all_fifo"]
    assert seen["demoted"] >= 1 and not seen["any_fifo_after"]  # 50 ms of CPU: over 30 % of a 100 ms window
