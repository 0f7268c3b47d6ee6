"""The soak's faults, each injected the way it happens on a show, detected by the daemon, and recovered by the soak's
operator client with the documented recovery (``docs/operations.md``: remove the cause, ``reset``, ``enable``).

A fault run records when it was injected, when the daemon said so (its ``fault`` event, or for request-level faults
the error replies), when the cause was removed and when the head was active again. Times are ``time.monotonic()``,
the daemon's clock too (one machine).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zmq

from benchmarks._soak_clients import Collector, emulators

#: How long the daemon has to notice a fault, and the operator to bring the head back.
DETECT_TIMEOUT_S = 20.0
RECOVER_TIMEOUT_S = 40.0


@dataclass
class FaultRun:
    """One injected fault and what came of it."""

    name: str
    what: str
    t_inject: float
    expect_fault: bool
    t_detected: float | None = None
    detected_by: str = ""
    t_cleared: float | None = None
    t_recovered: float | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        def rel(t: float | None) -> float | None:
            return None if t is None else round(t - self.t_inject, 3)

        return {"fault": self.name, "what": self.what, "t_inject": round(self.t_inject, 3),
                "detected": self.t_detected is not None, "time_to_fault_s": rel(self.t_detected),
                "detected_by": self.detected_by, "cleared_s": rel(self.t_cleared),
                "recovered": self.t_recovered is not None,
                "time_to_recover_s": None if self.t_recovered is None or self.t_cleared is None
                else round(self.t_recovered - self.t_cleared, 3), "notes": self.notes}


class Operator:
    """The soak's operator: a protocol client that recovers the head as the operations guide says."""

    def __init__(self, endpoint: str, collector: Collector, daemon_pid: int, log_dir: Path) -> None:
        from models.client import Client

        self.client = Client(endpoint, timeout=30.0)
        self.endpoint = endpoint
        self.collector = collector
        self.daemon_pid = daemon_pid
        self.log_dir = log_dir
        self.spawned: list[subprocess.Popen[bytes]] = []
        self._mine: dict[str, dict[str, Any]] = {}  # emulators this operator started again, by kind

    def close(self) -> None:
        self.client.close()
        for proc in self.spawned:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()

    def recover(self, run: FaultRun) -> None:
        """``reset`` until it succeeds (a bus may still be reopening), then ``enable``; the head active again."""
        end = time.monotonic() + RECOVER_TIMEOUT_S
        while time.monotonic() < end:
            if self.client.request("status")["lifecycle"] == "active":
                break
            reply = self.client.request("reset")
            if not reply.get("ok"):
                run.notes.append(f"reset: {(reply.get('error') or {}).get('message')}"[:200])
                time.sleep(0.5)
                continue
            reply = self.client.request("enable")
            if not reply.get("ok"):
                run.notes.append(f"enable: {(reply.get('error') or {}).get('message')}"[:200])
                time.sleep(0.5)
        if self.client.request("status")["lifecycle"] == "active":
            run.t_recovered = time.monotonic()
        if len(run.notes) > 6:
            run.notes[3:-2] = [f"... {len(run.notes) - 5} more"]

    def wait_fault(self, run: FaultRun, bus: str, match: str = "") -> None:
        """The daemon's ``fault`` event after the injection naming ``bus`` and, in its message, ``match``. A fault
        for another reason that comes first (the head can hold one fault at a time) is noted, recovered, and the
        wait goes on while the injected condition lasts."""
        end = time.monotonic() + DETECT_TIMEOUT_S
        seen: set[float] = set()
        while time.monotonic() < end:
            for e in self.collector.events_since(run.t_inject, "fault"):
                if e["t"] in seen:
                    continue
                seen.add(e["t"])
                text = f"{e.get('source')}: {e.get('message')}"
                if e.get("bus") == bus and match.lower() in text.lower():
                    run.t_detected = float(e["t"])
                    run.detected_by = f"fault event: {text}"[:240]
                    return
                run.notes.append(f"another fault came first: {text}"[:240])
                self.recover(FaultRun("other", text, float(e["t"]), True))
            time.sleep(0.05)
        run.notes.append(f"no fault event naming bus {bus} and {match!r} within {DETECT_TIMEOUT_S} s")

    def recover_unexpected(self, ask: bool = False) -> FaultRun | None:
        """A fault nobody injected (the head in FAULT between the injected ones): note it and recover, as an operator
        would. ``ask``: ask the daemon rather than trust the telemetry seen so far, and enable an inactive head (done
        before each injection, so that every injected fault meets an active head)."""
        if not ask and self.collector.lifecycle != "fault":
            return None
        st = self.client.request("status")
        if ask and st.get("lifecycle") == "inactive":
            self.recover(FaultRun("enable", "inactive head enabled", time.monotonic(), False))
            return None
        fault = st.get("fault")
        if st.get("lifecycle") != "fault" or not fault:
            return None
        t = float(fault.get("t", time.monotonic()))
        run = FaultRun("unexpected", f"{fault.get('source')}: {fault.get('message')}"[:240], t, True, t_detected=t,
                       detected_by="fault event", t_cleared=time.monotonic())
        self.recover(run)
        return run

    # ------------------------------------------------------------------ the faults
    def can_bus_killed(self) -> FaultRun:
        """The CANopen device server is killed (SIGKILL) and started again 2 s later where it was."""
        emu = emulators(self.daemon_pid).get("canopen") or self._respawned("canopen")
        run = FaultRun("can_bus_killed", "CANopen emulator SIGKILL, back after 2 s", time.monotonic(), True)
        os.kill(emu["pid"], signal.SIGKILL)
        self.wait_fault(run, "can0", "connection lost")
        time.sleep(max(0.0, run.t_inject + 2.0 - time.monotonic()))
        self._respawn(emu)
        run.t_cleared = time.monotonic()
        self.recover(run)
        return run

    def heartbeat_stopped(self) -> FaultRun:
        """Drive 1 (the jaw) stops producing heartbeats; they resume after the fault."""
        control = self._control("canopen")
        run = FaultRun("heartbeat_stopped", "CiA 402 drive 1 stops its heartbeat", time.monotonic(), True)
        self._inject(control, {"op": "inject", "fault": "stop_heartbeat", "device": 1}, run)
        self.wait_fault(run, "can0", "heartbeat")
        self._inject(control, {"op": "inject", "fault": "resume_heartbeat", "device": 1}, run)
        run.t_cleared = time.monotonic()
        self.recover(run)
        return run

    def servo_overloaded(self) -> FaultRun:
        """A Dynamixel servo reports overload; the condition is cleared after the fault."""
        control = self._control("dynamixel")
        device = self._first_servo(control)
        run = FaultRun("servo_overloaded", f"Dynamixel servo {device} overload", time.monotonic(), True)
        self._inject(control, {"op": "inject", "fault": "overload", "device": device}, run)
        self.wait_fault(run, "dxl", "overload")
        self._inject(control, {"op": "clear", "fault": "overload", "device": device}, run)
        run.t_cleared = time.monotonic()
        self.recover(run)
        return run

    def malformed_burst(self) -> FaultRun:
        """200 bad requests in a burst: not msgpack, not a map, unknown op, wrong fields, non-finite values."""
        run = FaultRun("malformed_burst", "200 malformed requests on the command socket", time.monotonic(), False)
        bad = [b"\xc1\xff garbage", msgpack.packb([1, 2, 3]), msgpack.packb({"op": "fly", "id": 1}),
               msgpack.packb({"op": "stream", "id": 2, "channels": ["jaw"], "frames": [[0.0]]}),
               msgpack.packb({"op": "stream", "id": 3, "channels": ["jaw"], "frames": [[0.0, float("nan")]]}),
               msgpack.packb({"op": "pose", "id": 4, "pose": {"nose": 3.0}}),
               msgpack.packb({"op": "record", "id": 5, "action": "start", "name": "../../etc"}),
               msgpack.packb({"id": 6}), b"", msgpack.packb({"op": "play", "id": 7, "clip": 12})]
        sock = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.endpoint)
        for i in range(200):
            sock.send(bad[i % len(bad)])
        errors = ok = 0
        end = time.monotonic() + 10.0
        while errors + ok < 200 and time.monotonic() < end:
            if sock.poll(100):
                reply = msgpack.unpackb(sock.recv(), raw=False)
                if isinstance(reply, dict) and reply.get("ok") is False:
                    errors += 1
                else:
                    ok += 1
        sock.close(0)
        run.notes.append(f"{errors} error replies, {ok} other replies, {200 - errors - ok} unanswered")
        if errors == 200:
            run.t_detected = time.monotonic()
            run.detected_by = "every request answered with an error naming it"
        run.t_cleared = time.monotonic()
        self._still_active(run)
        return run

    def client_vanished(self) -> FaultRun:
        """Clients that connect and vanish: a DEALER that streams and closes without reading its replies, a TCP
        connection cut in the middle of the ZeroMQ greeting, and one that sends a request's first bytes only."""
        run = FaultRun("client_vanished", "clients connect and vanish mid-exchange", time.monotonic(), False)
        sock = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.endpoint)
        now = time.monotonic()
        for k in range(20):
            sock.send(msgpack.packb({"op": "status", "id": k}))
        sock.send(msgpack.packb({"op": "stream", "id": 99, "channels": ["jaw"], "frames": [[now + 0.05, 1.0]]}))
        sock.close(0)
        host, port = self.endpoint.rsplit("/", 1)[1].rsplit(":", 1)
        for payload in (b"\xff\x00\x00\x00\x00\x00\x00\x00\x01\x7f", b"\xff\x00\x00\x00\x00\x00\x00\x00\x01\x7f\x03\x01"
                        b"NULL" + b"\x00" * 16):
            with socket.create_connection((host, int(port)), timeout=2.0) as raw:
                raw.sendall(payload)
        run.t_cleared = time.monotonic()
        run.t_detected = None
        run.detected_by = "nothing to detect: the daemon drops the connections"
        self._still_active(run)
        return run

    # ------------------------------------------------------------------ helpers
    def _still_active(self, run: FaultRun) -> None:
        """A request-level fault needs no recovery: the head must stay active, and answer."""
        time.sleep(1.0)
        st = self.client.request("status")
        if st.get("lifecycle") == "active" and not self.collector.events_since(run.t_inject, "fault"):
            run.t_recovered = time.monotonic()
        else:
            run.notes.append(f"head {st.get('lifecycle')} after the burst: {st.get('fault')}")
            self.recover(run)

    def _control(self, kind: str) -> str:
        emu = emulators(self.daemon_pid).get(kind) or self._respawned(kind)
        if not emu.get("control"):
            raise RuntimeError(f"the {kind} emulator has no control endpoint")
        return str(emu["control"])

    def _inject(self, control: str, message: dict[str, Any], run: FaultRun) -> None:
        from models.emulator_control import request

        reply = request(control, message, timeout_s=5.0)
        if not reply.get("ok", True):
            run.notes.append(f"emulator refused {message}: {reply}")

    def _first_servo(self, control: str) -> int:
        from models.emulator_control import request

        servos = request(control, {"op": "status"}, timeout_s=5.0).get("servos") or []
        return min((int(s["id"]) for s in servos), default=1)

    def _respawned(self, kind: str) -> dict[str, Any]:
        if kind in self._mine:
            return self._mine[kind]
        raise RuntimeError(f"no {kind} emulator found under the daemon (pid {self.daemon_pid})")

    def _respawn(self, emu: dict[str, Any]) -> None:
        """Start the emulator again with its command line, directory, environment and niceness."""
        log = (self.log_dir / f"emulator-{len(self.spawned)}.log").open("wb")
        nice = emu["nice"]
        proc = subprocess.Popen(emu["args"], cwd=emu["cwd"], env=emu["env"], stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, preexec_fn=lambda: _set_nice(nice))
        self.spawned.append(proc)
        end = time.monotonic() + 20.0
        path = Path(log.name)
        while time.monotonic() < end and b"ready:" not in path.read_bytes():
            if proc.poll() is not None:
                raise RuntimeError(f"restarted emulator exited: {path.read_text(errors='replace')[-400:]}")
            time.sleep(0.05)
        kind = "canopen" if "canopen" in emu["args"] else "dynamixel"
        self._mine[kind] = {**emu, "pid": proc.pid}


def _set_nice(nice: int) -> None:
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, nice)
