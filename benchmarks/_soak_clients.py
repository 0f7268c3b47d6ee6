"""The soak's clients and watchers: a performance streamer, an OSC cue sender, a telemetry collector, and the
daemon's processes and memory read from ``/proc``.

Each client runs on a thread of the soak's process with a socket of its own (the daemon sees separate clients).
The schedule decides who drives the head: the streamer streams the performance except in the OSC windows, where the
cue sender takes over (the last active source wins, ``docs/show_control.md``), as a show hands over between them.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zmq

#: The daemon's jitter-buffer delay (``[runtime] stream_delay_s``, the sample head's default).
STREAM_DELAY_S = 0.05

#: ``in_osc_window(t)``: whether the cue sender drives the head at soak time ``t`` (seconds from the start).
Schedule = Callable[[float], bool]


@dataclass
class StreamCounts:
    """What the streamer sent and what the daemon answered (frames, by the lifecycle seen when they were sent)."""

    sent: int = 0
    sent_active: int = 0  # sent while the collector last saw the head active
    replies: int = 0
    accepted: int = 0
    accepted_active: int = 0
    late: int = 0
    late_at: list[tuple[float, int]] = field(default_factory=list)  # (send time, frames late) of replies with late
    #: late frames that reached the daemon's server already older than its jitter buffer's delay (the sender or the
    #: machine held them, not the daemon's path to the loop)
    late_on_arrival: int = 0
    refused: dict[str, int] = field(default_factory=dict)  # error code -> requests


class Streamer(threading.Thread):
    """Streams ``clip`` (looped) at ``rate_hz``, one frame per request on a DEALER socket, without waiting for
    replies; pauses while ``schedule`` says the OSC sender drives."""

    def __init__(self, endpoint: str, clip: Any, rate_hz: float, t0: float, schedule: Schedule,
                 active: Callable[[], bool]) -> None:
        super().__init__(name="soak-streamer", daemon=True)
        self.endpoint, self.clip, self.rate_hz, self.t0 = endpoint, clip, rate_hz, t0
        self.schedule, self.active = schedule, active
        self.counts = StreamCounts()
        self.stop_event = threading.Event()
        self._active_ids: set[int] = set()
        self._sent_at: dict[int, float] = {}

    def run(self) -> None:
        names = sorted(self.clip.channels)
        sock = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.endpoint)
        ids = itertools.count(1)
        period = 1.0 / self.rate_hz
        deadline = time.monotonic()
        try:
            while not self.stop_event.is_set():
                now = time.monotonic()
                if not self.schedule(now - self.t0):
                    values = self.clip.sample((now - self.t0) % self.clip.duration)
                    rid = next(ids)
                    frame = [now, *(float(values[n]) for n in names)]
                    sock.send(msgpack.packb({"op": "stream", "id": rid, "channels": names, "frames": [frame]}))
                    self.counts.sent += 1
                    self._sent_at[rid] = now
                    if self.active():
                        self.counts.sent_active += 1
                        self._active_ids.add(rid)
                self._replies(sock)
                deadline += period
                wait = deadline - time.monotonic()
                if wait < -0.5:
                    deadline = time.monotonic()
                self.stop_event.wait(max(wait, 0.0))
            end = time.monotonic() + 1.0
            while time.monotonic() < end and self.counts.replies < self.counts.sent:
                if sock.poll(50):
                    self._replies(sock)
        finally:
            sock.close(0)

    def _replies(self, sock: zmq.Socket) -> None:
        c = self.counts
        while sock.poll(0):
            reply = msgpack.unpackb(sock.recv(), raw=False)
            c.replies += 1
            was_active = reply.get("id") in self._active_ids
            self._active_ids.discard(reply.get("id"))
            sent_at = self._sent_at.pop(reply.get("id"), math.nan)
            if reply.get("ok"):
                c.accepted += int(reply.get("accepted", 0))
                c.late += int(reply.get("late", 0))
                if reply.get("late"):
                    c.late_at.append((sent_at, int(reply["late"])))
                    if float(reply.get("t_recv", math.inf)) - sent_at > STREAM_DELAY_S:
                        c.late_on_arrival += int(reply["late"])
                if was_active:
                    c.accepted_active += int(reply.get("accepted", 0))
            else:
                code = str((reply.get("error") or {}).get("code"))
                c.refused[code] = c.refused.get(code, 0) + 1


class OscSender(threading.Thread):
    """A cue system: in the OSC windows, ``/face/jaw`` and ``/face/blink`` at ``rate_hz`` over UDP."""

    def __init__(self, port: int, rate_hz: float, t0: float, schedule: Schedule) -> None:
        super().__init__(name="soak-osc", daemon=True)
        self.port, self.rate_hz, self.t0, self.schedule = port, rate_hz, t0, schedule
        self.sent = 0
        self.stop_event = threading.Event()

    def run(self) -> None:
        from pythonosc.udp_client import SimpleUDPClient

        client = SimpleUDPClient("127.0.0.1", self.port)
        while not self.stop_event.wait(1.0 / self.rate_hz):
            t = time.monotonic() - self.t0
            if self.schedule(t):
                client.send_message("/face/jaw", 6.0 + 5.0 * math.sin(2.0 * math.pi * 0.5 * t))
                client.send_message("/face/blink", 10.0 + 10.0 * math.sin(2.0 * math.pi * 0.3 * t))
                self.sent += 2


class Collector(threading.Thread):
    """Keeps every telemetry event and a slim row of every ``state`` message: t, loop cycles and missed deadlines,
    lifecycle, jaw commanded and measured, the buses' feedback age."""

    def __init__(self, endpoint: str) -> None:
        super().__init__(name="soak-telemetry", daemon=True)
        self.endpoint = endpoint
        self.events: list[dict[str, Any]] = []
        self.states: list[tuple[float, int, int, str, float, float, float]] = []
        self.lifecycle = "unknown"
        self.stop_event = threading.Event()
        self.lock = threading.Lock()

    def run(self) -> None:
        from models.client import Telemetry

        with Telemetry(self.endpoint) as tel:
            while not self.stop_event.is_set():
                got = tel.recv(0.2)
                if got is None:
                    continue
                topic, msg = got
                with self.lock:
                    if topic == "event":
                        self.events.append(msg)
                        continue
                    self.lifecycle = str(msg.get("lifecycle"))
                    loop = msg.get("loop") or {}
                    age = msg.get("feedback_age_s") or {}
                    self.states.append((float(msg["t"]), int(loop.get("cycles", 0)), int(loop.get("missed", 0)),
                                        self.lifecycle, _num((msg.get("commanded") or {}).get("jaw")),
                                        _num((msg.get("measured") or {}).get("jaw")),
                                        max((_num(v) for v in age.values()), default=math.nan)))

    def active(self) -> bool:
        return self.lifecycle == "active"

    def events_since(self, t: float, kind: str | None = None) -> list[dict[str, Any]]:
        with self.lock:
            return [e for e in self.events if e.get("t", 0.0) >= t and (kind is None or e.get("event") == kind)]


def _num(value: Any) -> float:
    return math.nan if value is None else float(value)


# ---------------------------------------------------------------------- processes and memory
def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (from ``/proc``)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parents.items() if pp == p]
        out.extend(kids)
        todo.extend(kids)
    return out


def cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")[:-1]
    except OSError:
        return []


def is_emulator(pid: int) -> bool:
    args = cmdline(pid)
    return "sim" in args and ("canopen" in args or "dynamixel" in args)


def rss_mib(pid: int) -> float:
    """VmRSS of ``pid`` in MiB (0 if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def daemon_memory(pid: int) -> dict[str, float]:
    """VmRSS in MiB of the daemon's own processes (the daemon and its children but not the emulators, which stand in
    for hardware): per process (``name:pid``) and ``total``."""
    out: dict[str, float] = {}
    for p in [pid, *children(pid)]:
        if p != pid and is_emulator(p):
            continue
        args = cmdline(p)
        label = "daemon" if p == pid else (Path(args[0]).name if args else "?")
        out[f"{label}:{p}"] = rss_mib(p)
    out["total"] = sum(out.values())
    return out


def listening_ports(pid: int) -> set[int]:
    """TCP ports process ``pid`` listens on (its socket inodes matched in ``/proc/net/tcp``)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        cols = line.split()
        if cols[3] == "0A" and cols[9] in inodes:  # LISTEN
            ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


def emulators(pid: int) -> dict[str, dict[str, Any]]:
    """The daemon's emulator processes by kind (``canopen``, ``dynamixel``): pid, command line, control endpoint,
    working directory and environment (to start one again where it was)."""
    out: dict[str, dict[str, Any]] = {}
    for p in children(pid):
        args = cmdline(p)
        if not is_emulator(p):
            continue
        kind = "canopen" if "canopen" in args else "dynamixel"
        control = args[args.index("--control") + 1] if "--control" in args else None
        if "--port" in args:  # a restart must listen where the daemon's bus connects: the port it was given
            control_port = int(control.rsplit(":", 1)[1]) if control else -1
            ports = sorted(listening_ports(p) - {control_port})
            if ports:
                args = list(args)
                args[args.index("--port") + 1] = str(ports[0])
        env = dict(item.split("=", 1) for item in Path(f"/proc/{p}/environ").read_bytes().decode(
            errors="replace").split("\0") if "=" in item)
        out[kind] = {"pid": p, "args": args, "control": control, "cwd": os.readlink(f"/proc/{p}/cwd"), "env": env,
                     "nice": int(Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[16])}
    return out
