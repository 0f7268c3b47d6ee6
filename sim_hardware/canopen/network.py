"""A set of emulated CiA 402 drives on one python-can bus, stepped by a fixed-rate physics thread.

:class:`DriveSet` (alias :class:`CanOpenNetworkEmulator`) opens its own python-can bus (by default a
``virtual`` channel, so a master in the same process connects to the same channel name), hosts one
:class:`~sim_hardware.canopen.drive.EmulatedDrive` per node id on a canopen ``Network``, boots them
and steps their motor models at ``physics_hz`` against the real clock. Link impairments (drop,
corrupt, delay) are applied to every frame the drives send (``direction="tx"``), receive (``"rx"``)
or both; "corrupt" delivers the frame one byte short, the form a receiver can detect (bit errors
are rejected by the CAN controller's CRC and never reach software).

Given a ``transport`` at :meth:`DriveSet.start` (the socketcand server's ``publish``), the drives open no python-can
bus: their frames go straight to the transport and :meth:`DriveSet.deliver` hands them the clients' frames, so a
frame costs one function call instead of a deep copy, a queue and a thread switch. The physics thread wakes every
``tick_s`` (default 2 ms) and steps the motion at ``physics_hz`` in between; when it cannot keep that rate (the
process waited for a CPU) it logs a warning with the achieved rate and the longest stall, at most once per
:data:`RATE_WINDOW_S`, and :meth:`DriveSet.rate_report` gives the figures.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import random
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can
import canopen

from sim_hardware.canopen.drive import EMCY_GENERIC, EmulatedDrive
from sim_hardware.canopen.motor import MotorParams

log = logging.getLogger(__name__)

#: Seconds over which the physics thread judges whether it keeps its rate (and the most often it warns).
RATE_WINDOW_S = 2.0
#: A tick this late (seconds past its deadline) counts as a stall that the emulator reports.
STALL_WARN_S = 0.02

#: ``transport(can_id, data)``: where the drives' frames go when the drive set has no python-can bus.
Transport = Callable[[int, bytes], None]


@dataclass
class LinkImpairment:
    """Frame faults: probabilities per frame, a fixed delay, the direction and an optional node filter."""

    drop: float = 0.0
    corrupt: float = 0.0
    delay_s: float = 0.0
    direction: str = "tx"  # "tx" (drives → bus), "rx" (bus → drives) or "both"
    device: int | None = None  # only frames of this node id (COB-ID & 0x7F); None: all
    counts: dict[str, int] = field(default_factory=lambda: {"dropped": 0, "corrupted": 0, "delayed": 0})

    def active(self, rx: bool) -> bool:
        """Whether any fault is set for this direction (``rx``: frames towards the drives)."""
        if not (self.drop or self.corrupt or self.delay_s):
            return False
        return self.direction == "both" or self.direction == ("rx" if rx else "tx")

    def applies_to(self, can_id: int) -> bool:
        """Whether a frame with ``can_id`` matches the node filter (SYNC and NMT belong to no node)."""
        return self.device is None or (can_id & 0x7F == self.device and can_id not in (0, 0x80))


class _EmulatorNetwork(canopen.Network):
    """canopen ``Network`` whose sends and receptions pass through a :class:`LinkImpairment`."""

    NOTIFIER_CYCLE = 0.1  # bounded shutdown time

    def __init__(self, bus: can.BusABC | None, seed: int | None, transport: Transport | None = None) -> None:
        super().__init__(bus)
        self.transport = transport
        self.impairment = LinkImpairment()
        self._rng = random.Random(seed)
        self._delayed: list[tuple[float, int, bool, int, bytes]] = []
        self._seq = itertools.count()
        self._delay_lock = threading.Lock()

    def _impair(self, can_id: int, data: bytes, rx: bool) -> tuple[bytes | None, float]:
        imp = self.impairment
        if not imp.active(rx) or not imp.applies_to(can_id):
            return data, 0.0
        if imp.drop and self._rng.random() < imp.drop:
            imp.counts["dropped"] += 1
            return None, 0.0
        if imp.corrupt and self._rng.random() < imp.corrupt:
            imp.counts["corrupted"] += 1
            if not data:
                return None, 0.0
            data = bytes(data[:-1])
        if imp.delay_s > 0:
            imp.counts["delayed"] += 1
        return data, imp.delay_s

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        out, delay = self._impair(can_id, bytes(data), rx=False)
        if out is None:
            return
        if delay > 0:
            self._defer(delay, can_id, out, rx=False)
            return
        self._emit(can_id, out, remote)

    def _emit(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if self.transport is not None:
            self.transport(can_id, data)
        else:
            super().send_message(can_id, data, remote)

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        out, delay = self._impair(can_id, bytes(data), rx=True)
        if out is None:
            return
        if delay > 0:
            self._defer(delay, can_id, out, rx=True)
            return
        super().notify(can_id, bytearray(out), timestamp)

    def _defer(self, delay: float, can_id: int, data: bytes, rx: bool) -> None:
        with self._delay_lock:
            heapq.heappush(self._delayed, (time.monotonic() + delay, next(self._seq), rx, can_id, data))

    def flush_delayed(self, now: float) -> None:
        """Deliver delayed frames that are due (called by the physics thread)."""
        while True:
            with self._delay_lock:
                if not self._delayed or self._delayed[0][0] > now:
                    return
                _, _, rx, can_id, data = heapq.heappop(self._delayed)
            try:
                if rx:
                    super().notify(can_id, bytearray(data), time.time())
                else:
                    self._emit(can_id, data)
            except Exception:
                log.exception("delayed frame 0x%03X could not be delivered", can_id)


class DriveSet:
    """Emulated CiA 402 drives ``node_ids`` on one bus; use as a context manager or start()/stop().

    ``bus_kwargs`` go to ``can.Bus`` (default ``interface="virtual"``, ``channel``); a master in the
    same process opens ``can.Bus(interface="virtual", channel=<same name>)`` — for the Likeness
    driver that is ``canopen402`` with options ``{"interface": "virtual", "channel": <name>}``.
    """

    MAX_CATCHUP_STEPS = 50

    def __init__(
        self,
        node_ids: Iterable[int],
        *,
        channel: str = "likeness-can0",
        interface: str = "virtual",
        physics_hz: float = 1000.0,
        heartbeat_ms: int = 0,
        following_error_window: int = 5000,
        initial_positions: Mapping[int, float] | None = None,
        params: MotorParams | None = None,
        seed: int | None = None,
        bus_kwargs: Mapping[str, Any] | None = None,
        tick_s: float = 0.002,
    ) -> None:
        ids = sorted(set(node_ids))
        if not ids or any(not 1 <= n <= 127 for n in ids):
            raise ValueError(f"node ids must be 1..127, got {ids}")
        if physics_hz <= 0:
            raise ValueError(f"physics_hz must be positive, got {physics_hz}")
        if not 0 < tick_s <= 0.05:
            raise ValueError(f"tick_s must be in (0, 0.05], got {tick_s}")
        self.tick_s = max(tick_s, 1.0 / physics_hz)
        self.channel = channel
        self.interface = interface
        self.physics_hz = physics_hz
        self._bus_kwargs = dict(bus_kwargs or {})
        self._seed = seed
        initial_positions = initial_positions or {}
        self.drives: dict[int, EmulatedDrive] = {
            n: EmulatedDrive(
                n,
                params=params,
                initial_position_counts=initial_positions.get(n, 0.0),
                heartbeat_ms=heartbeat_ms,
                following_error_window=following_error_window,
            )
            for n in ids
        }
        self.network: _EmulatorNetwork | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.overruns = 0
        self._physics_lock = threading.Lock()
        self._physics_t = 0.0  # time.monotonic() the motion has been stepped to
        self._deliver_lock = threading.Lock()
        self._rate = _RateWatch(physics_hz)

    # ------------------------------------------------------------------ life cycle
    def start(self, transport: Transport | None = None) -> DriveSet:
        """Open the bus (or send through ``transport``, receiving through :meth:`deliver`), boot every drive (boot-up
        messages) and start the physics thread."""
        if self.network is not None:
            return self
        if transport is None:
            net = _EmulatorNetwork(can.Bus(interface=self.interface, channel=self.channel, **self._bus_kwargs),
                                   self._seed)
            net.connect()
        else:
            net = _EmulatorNetwork(None, self._seed, transport)
        self.network = net
        self._physics_t = time.monotonic()
        # Before the drives' own SYNC handlers: the motion is brought up to date, so the TPDOs a SYNC triggers report
        # where the drives are now even when the physics thread has been waiting for a CPU.
        net.subscribe(0x80, self._on_sync)
        for drive in self.drives.values():
            drive.attach(net)
        for drive in self.drives.values():
            drive.boot()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="canopen-drive-physics", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the physics thread and close the bus (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        net, self.network = self.network, None
        if net is not None:
            with self._deliver_lock:
                for drive in self.drives.values():
                    drive.detach()
            if net.transport is None:
                net.disconnect()

    def deliver(self, can_id: int, data: bytes, timestamp: float) -> None:
        """A frame from the bus to the drives (the socketcand server's ``on_frame``); one frame at a time, as a CAN
        controller hands them over. Remote and error frames never come here."""
        with self._deliver_lock:
            net = self.network
            if net is not None:
                net.notify(can_id, bytearray(data), timestamp)

    def __enter__(self) -> DriveSet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def advance(self, now: float) -> None:
        """Step every drive's motion up to ``now`` (at most :data:`MAX_CATCHUP_STEPS` steps; time beyond that is
        dropped and counted in ``overruns`` and in the rate report)."""
        dt = 1.0 / self.physics_hz
        with self._physics_lock:
            steps = int((now - self._physics_t) / dt)
            if steps > self.MAX_CATCHUP_STEPS:
                self.overruns += 1
                self._rate.dropped += steps - self.MAX_CATCHUP_STEPS
                self._physics_t = now - self.MAX_CATCHUP_STEPS * dt
                steps = self.MAX_CATCHUP_STEPS
            if steps > 0:
                for drive in self.drives.values():
                    drive.step(dt, steps)
                self._physics_t += steps * dt
                self._rate.stepped += steps

    def rate_report(self) -> dict[str, float]:
        """The physics rate kept over the last full window: ``physics_hz``, ``achieved_hz``, ``max_late_ms``,
        ``dropped_steps``, ``windows_behind`` (how many windows fell short since start)."""
        return self._rate.report()

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        self.advance(time.monotonic())

    def _run(self) -> None:
        dt = self.tick_s
        drives = list(self.drives.values())
        deadline = time.monotonic()
        self._rate.start(deadline)
        while not self._stop.is_set():
            now = time.monotonic()
            self._rate.tick(now, now - deadline)
            self.advance(now)
            net = self.network
            if net is None:
                break
            try:
                for drive in drives:
                    drive.step_comm(now)
                net.flush_delayed(now)
            except Exception:  # a send can fail while the bus shuts down
                if not self._stop.is_set():
                    log.exception("drive set: communication step failed")
            deadline += dt
            wait = deadline - time.monotonic()
            if wait < -STALL_WARN_S:
                deadline = time.monotonic()
            self._stop.wait(max(wait, 0.0))

    # ------------------------------------------------------------------ fault injection
    def drive(self, node_id: Any) -> EmulatedDrive:
        """The drive with ``node_id`` (ValueError naming it if there is none)."""
        try:
            return self.drives[int(node_id)]
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"no emulated drive with node id {node_id!r}; nodes: {sorted(self.drives)}") from None

    def set_link(self, **settings: Any) -> LinkImpairment:
        """Replace the link impairment: ``drop``, ``corrupt`` (0..1), ``delay_ms``, ``direction``, ``device``."""
        if self.network is None:
            raise RuntimeError("drive set is not started")
        allowed = {"drop", "corrupt", "delay_ms", "direction", "device", "seed"}
        unknown = set(settings) - allowed
        if unknown:
            raise ValueError(f"unknown frame-fault settings {sorted(unknown)}; allowed: {sorted(allowed)}")
        drop = float(settings.get("drop", 0.0))
        corrupt = float(settings.get("corrupt", 0.0))
        delay = float(settings.get("delay_ms", 0.0)) / 1000.0
        direction = str(settings.get("direction", "tx"))
        for key, value in (("drop", drop), ("corrupt", corrupt)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{key} must be a probability in [0, 1], got {value}")
        if not 0.0 <= delay <= 5.0:
            raise ValueError(f"delay_ms must be in [0, 5000], got {delay * 1000}")
        if direction not in ("tx", "rx", "both"):
            raise ValueError(f"direction must be 'tx', 'rx' or 'both', got {direction!r}")
        device = settings.get("device")
        if device is not None:
            device = self.drive(device).node_id
        if "seed" in settings:
            self.network._rng.seed(int(settings["seed"]))
        imp = LinkImpairment(drop=drop, corrupt=corrupt, delay_s=delay, direction=direction, device=device)
        self.network.impairment = imp
        return imp

    def inject(self, fault: str, **params: Any) -> dict[str, Any]:
        """Apply one named fault; returns a reply map. See :data:`FAULTS` for names and parameters."""
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; known: {', '.join(sorted(FAULTS))}")
        if fault == "frames":
            imp = self.set_link(**params)
            return {"drop": imp.drop, "corrupt": imp.corrupt, "delay_ms": imp.delay_s * 1000.0,
                    "direction": imp.direction, "device": imp.device}
        if fault == "clear":
            if self.network is not None:
                self.network.impairment = LinkImpairment()
            for drive in self.drives.values():
                drive.heartbeat_enabled = True
                drive.feedback_frozen = False
                drive.set_jammed(False)
                drive.set_slipping(False)
            return {}
        if fault == "status":
            return {"drives": self.status()}
        drive = self.drive(params.pop("device", None))
        if fault == "stop_heartbeat":
            drive.heartbeat_enabled = False
        elif fault == "resume_heartbeat":
            drive.heartbeat_enabled = True
        elif fault == "drive_fault":
            code = int(params.pop("code", EMCY_GENERIC))
            if not 0 < code <= 0xFFFF:
                raise ValueError(f"code must be a 16-bit EMCY error code, got {code}")
            drive.raise_fault(code)
        elif fault == "jam":
            drive.set_jammed(True)
        elif fault == "release":
            drive.set_jammed(False)
            drive.set_slipping(False)
        elif fault == "freeze_feedback":
            drive.feedback_frozen = True
        elif fault == "resume_feedback":
            drive.feedback_frozen = False
        elif fault == "slip":
            drive.set_slipping(True)
        elif fault == "following_error":
            counts = float(params.pop("counts", 2 * drive._fe_window))
            drive.set_jammed(True, offset_counts=counts)
        if params:
            raise ValueError(f"fault {fault!r} got unknown parameters {sorted(params)}")
        return {"device": drive.node_id, "state": drive.state}

    def handle_control(self, request: Mapping[str, Any]) -> dict[str, Any]:
        """``ControlServer`` handler: ``{"op": "inject", "fault": NAME, ...params}`` or ``{"op": "status"}``."""
        req = dict(request)
        op = req.pop("op", "inject")
        if op == "status":
            return {"drives": self.status(), "rate": self.rate_report()}
        if op == "positions":
            return {"positions": {str(n): d.position_counts for n, d in self.drives.items()}}
        if op != "inject":
            raise ValueError(f"unknown op {op!r}; known: inject, status, positions")
        fault = req.pop("fault", None)
        if not isinstance(fault, str):
            raise ValueError("inject needs a 'fault' name")
        return self.inject(fault, **req)

    def status(self) -> dict[str, dict[str, Any]]:
        """Per-drive ground truth (string keys, msgpack-friendly)."""
        return {
            str(n): {
                "state": d.state,
                "nmt": d.nmt_state,
                "position_counts": d.position_counts,
                "velocity_counts": d.velocity_counts,
                "heartbeat": d.heartbeat_enabled,
                "jammed": d.jammed,
                "feedback_frozen": d.feedback_frozen,
                "slipping": d.slipping,
            }
            for n, d in self.drives.items()
        }


class _RateWatch:
    """Whether the physics thread keeps ``physics_hz``: steps done and ticks' lateness per :data:`RATE_WINDOW_S`
    window; a window that falls short (under 95 % of the rate, steps dropped, or a tick over :data:`STALL_WARN_S`
    late) is logged as a warning with the achieved rate."""

    def __init__(self, physics_hz: float) -> None:
        self.physics_hz = physics_hz
        self.stepped = 0  # counted by DriveSet.advance
        self.dropped = 0
        self._window_start = 0.0
        self._max_late = 0.0
        self.windows_behind = 0
        self._last: dict[str, float] = {"physics_hz": physics_hz, "achieved_hz": physics_hz, "max_late_ms": 0.0,
                                        "dropped_steps": 0, "windows_behind": 0}

    def start(self, now: float) -> None:
        self._window_start = now
        self.stepped = self.dropped = 0
        self._max_late = 0.0

    def tick(self, now: float, late: float) -> None:
        """One physics tick ``late`` seconds after its deadline; closes the window when it is over."""
        self._max_late = max(self._max_late, late)
        span = now - self._window_start
        if span < RATE_WINDOW_S:
            return
        achieved = self.stepped / span
        behind = achieved < 0.95 * self.physics_hz or self.dropped > 0 or self._max_late > STALL_WARN_S
        self.windows_behind += behind
        self._last = {"physics_hz": self.physics_hz, "achieved_hz": round(achieved, 1),
                      "max_late_ms": round(1000.0 * self._max_late, 2), "dropped_steps": self.dropped,
                      "windows_behind": self.windows_behind}
        if behind:
            log.warning("canopen emulator behind its %.0f Hz physics rate: achieved %.0f Hz over %.1f s, longest stall "
                        "%.0f ms, %d steps dropped", self.physics_hz, achieved, span, 1000.0 * self._max_late,
                        self.dropped)
        self.start(now)

    def report(self) -> dict[str, float]:
        return dict(self._last)


#: Fault names accepted by :meth:`DriveSet.inject` and their parameters.
FAULTS: dict[str, str] = {
    "stop_heartbeat": "device=N: the drive stops producing heartbeats (everything else keeps working)",
    "resume_heartbeat": "device=N: heartbeats resume",
    "drive_fault": "device=N [code=0x1000]: the drive faults and sends EMCY code",
    "jam": "device=N: the rotor is blocked (following error builds up when it is commanded to move)",
    "release": "device=N: unblock the rotor and end a slip",
    "freeze_feedback": "device=N: the drive ignores SYNCs: no TPDOs, no new targets (heartbeat and SDO go on)",
    "resume_feedback": "device=N: TPDOs resume",
    "slip": "device=N: the reported position stays where it is while the motor follows (the drive sees no error)",
    "following_error": "device=N [counts=2*window]: the rotor is knocked off by counts and blocked",
    "frames": "[drop=P] [corrupt=P] [delay_ms=D] [direction=tx|rx|both] [device=N] [seed=S]: link faults",
    "clear": "remove link faults, jams, slips, frozen feedback and heartbeat stops",
    "status": "report every drive's state",
}

CanOpenNetworkEmulator = DriveSet
