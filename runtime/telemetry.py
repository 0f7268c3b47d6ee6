"""The API server's telemetry: the PUB socket, and the formatting of the core's state snapshots for clients.

The core hands over raw snapshots (SI arrays, :class:`runtime.loop_messages.StateSnapshot`); here they become the
protocol's ``state`` messages: positions in the configured units, the loop's statistics, link poses m(q) of the
attachment links and the full skin-strain check of the commanded pose (both a millisecond or so, so they run on a
thread of their own, :class:`LatestWorker`, which keeps only the newest snapshot). Events pass straight through.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, TypeVar

import numpy as np
import zmq

from models import protocol as P
from models.headspec import HeadSpec
from runtime.core.events import Body

if TYPE_CHECKING:
    from models.linkmap import LinkMap
    from runtime.strain_check import FullStrainCheck

log = logging.getLogger(__name__)

T = TypeVar("T")
#: Status keys passed from the core's reply as they are.
STATUS_KEYS = ("estop", "fault", "moving", "timeline", "stream", "recording", "pose_reached", "pose_settled", "extra",
               "clip_bytes", "guard", "source", "clock", "live")
#: Snapshot keys passed into the ``state`` message as they are.
STATE_KEYS = ("clip", "stream", "extra", "guard", "source", "clock", "live")


@dataclass(frozen=True)
class ActuatorUnits:
    """SI ↔ the head's configured units (degrees, mm...), per actuator, in the head's order."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    inv_scale: np.ndarray  # configured units per SI unit

    @classmethod
    def of(cls, head: HeadSpec) -> ActuatorUnits:
        return cls(tuple(head.actuator_names), tuple(a.unit for a in head.actuators),
                   1.0 / np.array([a.unit_scale for a in head.actuators]))

    def named(self, si: object) -> dict[str, float | None]:
        """SI values → {actuator: value in its unit} (None where not finite)."""
        vals = (np.asarray(si) * self.inv_scale).tolist()
        return {n: (v if math.isfinite(v) else None) for n, v in zip(self.names, vals, strict=True)}


class LatestWorker(Generic[T]):
    """A thread that runs ``work`` on the latest item put, dropping any it had no time for (telemetry snapshots:
    only the newest matters), so slow formatting never delays the requests handled on the calling thread."""

    def __init__(self, work: Callable[[T], None], name: str) -> None:
        self._work = work
        self._cond = threading.Condition()
        self._item: T | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item: T) -> None:
        with self._cond:
            self._item = item
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._item is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                item, self._item = self._item, None
            try:
                self._work(item)
            except Exception:
                log.exception("telemetry failed")


class Telemetry:
    """Publishes events and state on the PUB socket (shared by the request and telemetry threads, under a lock),
    and keeps what the loop last said of itself (:attr:`loop`, :attr:`realtime`) for ``status`` and ``state``."""

    # Both results below cost about a millisecond each (a full predictor pass; m(p) per link) and the pose they
    # depend on stands still most of the time: each is recomputed only when its pose moved.
    _links_cache: tuple[bytes, dict[str, list[float]]] | None = None
    _guard_cache: tuple[bytes, Body] | None = None

    def __init__(self, pub: zmq.Socket, head: HeadSpec, units: ActuatorUnits,
                 strain_check: FullStrainCheck | None = None) -> None:
        self.pub = pub
        self.units = units
        self.linkmap = _load_linkmap(head)
        # the full strain check, confirming the loop's reduced one: NumPy arrays from the daemon's guard, so this
        # process never loads onnxruntime or scipy (runtime.strain_check)
        self.guard = strain_check
        self.guard_mismatch = 0
        self.loop: Body = {}  # the loop's statistics, summarised (runtime.loop_messages.LoopStatistics)
        self.realtime = "not started"
        self._lock = threading.Lock()
        self._worker = LatestWorker(self._publish_state, "telemetry")

    def close(self) -> None:
        self._worker.close()

    def event(self, body: Body) -> None:
        """Publish an event now."""
        self.publish(P.TOPIC_EVENT, body)

    def state(self, snapshot: Body) -> None:
        """Publish the state of ``snapshot`` soon, on the telemetry thread (a newer one replaces it)."""
        self._worker.put(snapshot)

    def common(self, snap: Body) -> Body:
        """The fields ``status`` replies and ``state`` messages share."""
        return {"t": snap["t"], "lifecycle": snap["lifecycle"], "mode": snap["mode"],
                "commanded": self.units.named(snap["commanded_si"]), "measured": self.units.named(snap["measured_si"]),
                "buses": snap["buses"], "connected": snap["connected"], "connection": snap.get("connection", {}),
                "feedback_age_s": snap["feedback_age"],
                "following_error": self.units.named(snap["following_error_si"])}

    def status(self, body: Body) -> Body:
        """A ``status`` reply from the core's answer: units, the loop's statistics and realtime state."""
        out = self.common(body)
        for key in STATUS_KEYS:
            if key in body:
                out[key] = body[key]
        out["loop"] = self.loop
        out["realtime"] = self.realtime
        return out

    def state_message(self, snap: Body) -> Body:
        """The ``state`` message of a snapshot: link poses m(q) and the full strain check included."""
        msg = self.common(snap)
        msg["loop"] = self.loop
        for key in STATE_KEYS:
            if key in snap:
                msg[key] = snap[key]
        measured = np.asarray(snap["measured_si"])
        if self.linkmap is not None and np.isfinite(measured).all():
            msg["links"] = self._link_poses(measured)
        if self.guard is not None and snap["lifecycle"] == "active":
            msg["guard_full"] = self._confirm_guard(snap["t"], np.asarray(snap["commanded_si"]))
        return msg

    def publish(self, topic: bytes, msg: Body) -> None:
        data = P.pack(plain(msg))
        try:
            with self._lock:
                self.pub.send_multipart([topic, data], zmq.NOBLOCK)
        except zmq.Again:
            pass
        except zmq.ZMQError as exc:
            log.warning("telemetry publish failed: %s", exc)

    def _publish_state(self, snap: Body) -> None:
        self.publish(P.TOPIC_STATE, self.state_message(snap))

    def _confirm_guard(self, t: object, q: np.ndarray) -> Body:
        """Full strain check of the commanded pose (off the loop): its strain range, and an event when the loop's
        reduced check decided otherwise (once per pose)."""
        assert self.guard is not None
        key = np.asarray(q, dtype=np.float64).tobytes()
        if self._guard_cache is not None and self._guard_cache[0] == key:
            return {**self._guard_cache[1], "mismatches": self.guard_mismatch}
        strain = self.guard.full(q)
        full_ok = bool(self.guard.passes(strain) and self.guard.in_range(q))
        reduced_ok = bool(self.guard.check(q))
        if full_ok != reduced_ok:
            self.guard_mismatch += 1
            self.event({"event": "skin_guard", "t": t, "full": full_ok, "reduced": reduced_ok,
                        "strain": [float(strain[0]), float(strain[1])], "mismatches": self.guard_mismatch})
        out: Body = {"ok": full_ok, "strain": [round(float(strain[0]), 4), round(float(strain[1]), 4)],
                        "mismatches": self.guard_mismatch}
        self._guard_cache = (key, out)
        return dict(out)

    def _link_poses(self, q: np.ndarray) -> dict[str, list[float]]:
        """Predicted attachment-link poses m(q) at measured actuator values: [x, y, z (m), rotation vector]."""
        from models.rigid import matrix_to_rotvec

        assert self.linkmap is not None
        key = np.asarray(q, dtype=np.float64).tobytes()
        if self._links_cache is not None and self._links_cache[0] == key:
            return self._links_cache[1]
        poses = self.linkmap.poses(dict(zip(self.units.names, q.tolist(), strict=True)))
        out = {name: [*T[:3, 3].tolist(), *matrix_to_rotvec(T[:3, :3]).tolist()] for name, T in poses.items()}
        self._links_cache = (key, out)
        return out


def plain(obj: object) -> object:
    """numpy scalars and arrays → Python values msgpack can carry."""
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _load_linkmap(head: HeadSpec) -> LinkMap | None:
    from models.linkmap import LinkMap

    path = head.path("linkmap")
    if path is None or not path.exists():
        return None
    return LinkMap.for_head(head)

