"""The live link: while Blender plays or scrubs, each shown frame's actuator pose is streamed to a running daemon
(the protocol's ``stream`` request), and an E-stop goes out on a socket of its own.

Timestamps follow the timeline, not the moment a frame happened to be drawn: a frame is stamped
``anchor_time + (frame − anchor_frame) / fps``, so a head fed at real-time playback moves with the timeline's exact
spacing and never drifts from it. The anchor is set ``lead`` seconds ahead of now (on the daemon's clock, through the
protocol's ``clock`` exchange) when the link starts, when the timeline jumps (a scrub, a loop back) and whenever the
stamps would fall more than ``tolerance`` seconds from ``now + lead`` (Blender playing slower or faster than real
time), so the head neither lags far behind the picture nor gets frames the daemon would call late. The daemon plays
a frame ``stream_delay_s`` after its stamp. Sending runs on a thread of its own: Blender's frame handler only stamps
and queues.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.client import Client, DaemonError, DaemonTimeout


@dataclass
class FrameClock:
    """Maps timeline frames to local monotonic times (see the module's docstring)."""

    lead: float = 0.08
    tolerance: float = 0.1
    anchor_frame: float | None = None
    anchor_time: float = 0.0
    last_frame: float | None = None
    last_time: float = -float("inf")
    anchors: int = 0

    def stamp(self, frame: float, fps: float, now: float) -> float:
        """The local time at which ``frame`` should show on the head."""
        step = 1.0 / fps
        # Forward steps up to half a second are playback (Blender skips frames to keep up with real time or with
        # its audio); anything else is a jump. Drift either way is caught by the tolerance below.
        jumped = self.last_frame is None or not (0 < frame - self.last_frame <= max(2.0, 0.5 * fps))
        if self.anchor_frame is not None and not jumped:
            t = self.anchor_time + (frame - self.anchor_frame) * step
            if abs(t - (now + self.lead)) <= self.tolerance:
                self.last_frame, self.last_time = frame, t
                return t
        anchor = now + self.lead
        if not jumped:  # playing on: never stamp before a frame already sent
            anchor = max(anchor, self.last_time + 1e-3)
        self.anchor_frame, self.anchor_time, self.last_frame, self.last_time = frame, anchor, frame, anchor
        self.anchors += 1
        return anchor


@dataclass
class LinkStats:
    """What the link has sent and what the daemon said."""

    frames: int = 0
    requests: int = 0
    accepted: int = 0
    late: int = 0
    refused: int = 0
    last_error: str = ""
    sent: list[tuple[float, float]] = field(default_factory=list)  # (daemon time, frame), the latest few hundred


@dataclass(frozen=True)
class _Frame:
    t: float  # daemon time
    frame: float
    values: list[float]


@dataclass(frozen=True)
class _Call:
    op: str
    fields: dict[str, Any]
    done: queue.Queue[dict[str, Any] | BaseException]


class LiveLink:
    """Streams actuator poses to a daemon with timeline timestamps; :meth:`estop` uses a socket of its own."""

    def __init__(self, endpoint: str, channels: Sequence[str], lead: float = 0.08, tolerance: float = 0.1,
                 timeout: float = 2.0, client_key: str | Path | None = None,
                 server_key: str | Path | None = None) -> None:
        self.endpoint = endpoint
        self.channels = list(channels)
        self.clock = FrameClock(lead=lead, tolerance=tolerance)
        self.stats = LinkStats()
        keys = {"client_key": client_key, "server_key": server_key}
        self._client = Client(endpoint, timeout=timeout, **keys)
        self._estop = Client(endpoint, timeout=timeout, **keys)
        try:
            self.hello = self._client.call("hello", client="likeness-blender")
            known = set(self.hello["head"]["channels"])
            missing = [c for c in self.channels if c not in known]
            if missing:
                raise ValueError(f"{endpoint}: the daemon's head has no channel(s) {missing}")
            self.offset, self.rtt = self._client.clock_offset()
        except BaseException:
            self._client.close()
            self._estop.close()
            raise
        self._queue: queue.Queue[_Frame | _Call | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="likeness-blender-live", daemon=True)
        self._thread.start()

    def call(self, op: str, **fields: Any) -> dict[str, Any]:
        """One request on the link's own socket, between frames (enable, reset, status)."""
        call = _Call(op, fields, queue.Queue())
        self._queue.put(call)
        out = call.done.get(timeout=30)
        if isinstance(out, BaseException):
            raise out
        return out

    def frame(self, frame: float, fps: float, values: Sequence[float]) -> float:
        """Stamp and queue one frame's channel values; returns its daemon time."""
        t = self.clock.stamp(frame, fps, time.monotonic()) + self.offset
        self._queue.put(_Frame(t, frame, [float(v) for v in values]))
        return t

    def estop(self, reason: str = "Blender E-stop") -> dict[str, Any]:
        """Latch the daemon's e-stop now, on the dedicated socket (never behind queued frames)."""
        return self._estop.call("estop", reason=reason)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=5)
        self._client.close()
        self._estop.close()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            batch: list[_Frame] = []
            while item is not None:
                if isinstance(item, _Call):  # send what is queued first, then the call
                    self._send(batch)
                    batch = []
                    self._answer(item)
                else:
                    batch.append(item)
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
            self._send(batch)
            if item is None:
                return

    def _answer(self, call: _Call) -> None:
        try:
            call.done.put(self._client.call(call.op, **call.fields))
        except (DaemonError, DaemonTimeout) as exc:
            call.done.put(exc)

    def _send(self, batch: list[_Frame]) -> None:
        if not batch:
            return
        batch.sort(key=lambda x: x.t)
        frames: list[list[float]] = []
        last = -float("inf")
        for fr in batch:  # strictly increasing stamps (a re-anchor can repeat one)
            if fr.t > last:
                frames.append([fr.t, *fr.values])
                last = fr.t
                self.stats.sent.append((fr.t, fr.frame))
        del self.stats.sent[:-500]
        self.stats.frames += len(frames)
        self.stats.requests += 1
        try:
            reply = self._client.call("stream", channels=self.channels, frames=frames)
        except (DaemonError, DaemonTimeout) as exc:
            self.stats.refused += len(frames)
            self.stats.last_error = str(exc)
            return
        self.stats.accepted += int(reply.get("accepted", 0))
        self.stats.late += int(reply.get("late", 0))
