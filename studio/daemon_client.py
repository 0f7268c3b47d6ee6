"""The studio as a client of the daemon, through the public protocol only (:mod:`models.client`).

One DEALER socket carries ordinary requests (under a lock: the page's callbacks run on several threads); the E-stop
has a DEALER socket of its own, so it never waits behind another request. A background thread reads telemetry
(``state`` and ``event``) into a short history of commanded and measured positions per channel, the latest loop
statistics and an event log, and asks for ``status`` twice a second for what telemetry does not carry (bus states,
faults, the guard's verdict).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.client import Client, DaemonError, DaemonTimeout, Telemetry

#: Seconds of telemetry kept for the traces.
HISTORY_S = 12.0
#: Events kept for the log.
EVENTS_KEPT = 40


@dataclass
class Mirror:
    """What the studio knows of the daemon: the latest state and status, traces and events."""

    connected: bool = False
    lifecycle: str = "unknown"
    mode: str = ""
    loop: dict[str, Any] = field(default_factory=dict)
    clip: dict[str, Any] | None = None
    status: dict[str, Any] = field(default_factory=dict)
    last_state_t: float = 0.0  # local monotonic time of the last state message
    times: collections.deque = field(default_factory=lambda: collections.deque(maxlen=2000))
    commanded: collections.deque = field(default_factory=lambda: collections.deque(maxlen=2000))
    measured: collections.deque = field(default_factory=lambda: collections.deque(maxlen=2000))
    events: collections.deque = field(default_factory=lambda: collections.deque(maxlen=EVENTS_KEPT))
    estop_reported: bool = False


class DaemonConnection:
    """Connection to one daemon: requests, a dedicated E-stop socket and a telemetry mirror."""

    def __init__(self, endpoint: str, telemetry: str | None = None, client_key: str | Path | None = None,
                 server_key: str | Path | None = None, timeout: float = 5.0) -> None:
        self.endpoint = endpoint
        self._keys = {"client_key": client_key, "server_key": server_key}
        self._client = Client(endpoint, timeout=timeout, **self._keys)
        self._estop = Client(endpoint, timeout=timeout, **self._keys)
        self._lock = threading.Lock()
        self._estop_lock = threading.Lock()
        self.hello = self.call("hello", client="likeness-studio")
        self.telemetry_endpoint = telemetry or str(self.hello["telemetry"])
        self.channels: dict[str, str] = dict(self.hello["head"]["channels"])
        self.mirror = Mirror(connected=True)
        self._mirror_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="studio-telemetry", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ requests
    def call(self, op: str, **fields: Any) -> dict[str, Any]:
        """One request; raises :class:`models.client.DaemonError` (with the protocol's code) on an error reply."""
        with self._lock:
            return self._client.call(op, **fields)

    def estop(self, reason: str = "studio E-stop") -> dict[str, Any]:
        """Latch the daemon's e-stop over the dedicated socket (never queued behind other requests)."""
        with self._estop_lock:
            return self._estop.call("estop", reason=reason)

    def send_clip(self, clip: dict[str, Any]) -> dict[str, Any]:
        return self.call("load_clip", clip=clip)

    def play(self, name: str, loop: bool = False, speed: float = 1.0) -> dict[str, Any]:
        return self.call("play", clip=name, loop=loop, speed=speed)

    # ------------------------------------------------------------------ telemetry
    def snapshot(self) -> Mirror:
        """A copy of the mirror (its deques copied) for drawing."""
        with self._mirror_lock:
            m = self.mirror
            return Mirror(m.connected, m.lifecycle, m.mode, dict(m.loop), m.clip, dict(m.status), m.last_state_t,
                          collections.deque(m.times), collections.deque(m.commanded), collections.deque(m.measured),
                          collections.deque(m.events), m.estop_reported)

    def _run(self) -> None:
        next_status = 0.0
        with Telemetry(self.telemetry_endpoint, **self._keys) as tel:
            while not self._stop.is_set():
                msg = tel.recv(0.1)
                if msg is not None:
                    self._take(*msg)
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + 0.5
                    self._poll_status()

    def _poll_status(self) -> None:
        try:
            st = self.call("status")
        except (DaemonError, DaemonTimeout) as exc:
            with self._mirror_lock:
                self.mirror.connected = False
                self.mirror.status = {"error": str(exc)}
            return
        with self._mirror_lock:
            self.mirror.connected = True
            self.mirror.status = st
            self.mirror.lifecycle = st.get("lifecycle", self.mirror.lifecycle)
            self.mirror.estop_reported = st.get("lifecycle") == "estop"

    def _take(self, topic: str, msg: dict[str, Any]) -> None:
        with self._mirror_lock:
            m = self.mirror
            if topic == "state":
                m.connected = True
                m.last_state_t = time.monotonic()
                m.lifecycle = msg.get("lifecycle", m.lifecycle)
                m.mode = msg.get("mode", m.mode)
                m.loop = dict(msg.get("loop") or {})
                m.clip = msg.get("clip")
                m.times.append(float(msg.get("t", 0.0)))
                m.commanded.append(dict(msg.get("commanded") or {}))
                m.measured.append(dict(msg.get("measured") or {}))
                horizon = m.times[-1] - HISTORY_S
                while m.times and m.times[0] < horizon:
                    m.times.popleft()
                    m.commanded.popleft()
                    m.measured.popleft()
                m.estop_reported = m.lifecycle == "estop"
            elif topic == "event":
                m.events.append(msg)
                if msg.get("event") == "estop":
                    m.estop_reported = True
                if msg.get("event") == "lifecycle":
                    m.lifecycle = msg.get("state", m.lifecycle)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._client.close()
        self._estop.close()
