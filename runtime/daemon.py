"""The realtime daemon: lifecycle, the fixed-rate control loop and the ZeroMQ command and telemetry sockets.

Each cycle: read drivers → evaluate the timeline (clip, stream jitter buffer, pose, neutral) at show time → solve
channels to actuator targets → safety (limits, groups, rate shaping) → write drivers → record → publish telemetry.
The control thread owns the PUB socket; the API thread owns the ROUTER socket and changes state under one lock that
the control thread also takes for each cycle. Lifecycle (after ros2_control): inactive (buses open, torque off) →
active (commanding) → fault (stop commanding; torque off as configured) or estop (latched); ``reset`` → inactive.
"""

from __future__ import annotations

import collections
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import zmq

from drivers.base import LifecycleState
from drivers.errors import BusError
from models.headspec import HeadSpec
from runtime import protocol as P
from runtime.config import DaemonConfig, daemon_config, resolve
from runtime.curves import ClipError, clip_from_dict
from runtime.hardware import Hardware
from runtime.loop import (
    LoopStats,
    RateScheduler,
    SwitchInterval,
    drop_realtime,
    freeze_heap,
    promote_threads,
    try_realtime,
)
from runtime.protocol import Fields, ProtocolError
from runtime.recording import Recorder
from runtime.safety import SafetyFilter
from runtime.solve import Solver, TargetSolver, UnknownChannel
from runtime.timeline import JitterBuffer, Timeline

log = logging.getLogger(__name__)

INACTIVE, ACTIVE, FAULT, ESTOP, UNCONFIGURED = "inactive", "active", "fault", "estop", "unconfigured"
MAX_STREAM_FRAMES_PER_REQUEST = 10_000
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


class Daemon:
    """One head's daemon. ``start()`` opens the buses and serves; ``stop()`` disables torque and closes everything."""

    def __init__(
        self,
        head: HeadSpec,
        overrides: Mapping[str, Any] | None = None,
        hardware: Hardware | None = None,
        target_solvers: Iterable[TargetSolver] = (),
    ) -> None:
        self.head = head
        self.cfg: DaemonConfig = daemon_config(head, overrides)
        self.hw = hardware if hardware is not None else Hardware.from_head(head)
        self.names = head.actuator_names
        self.units = [a.unit for a in head.actuators]
        self._scale = np.array([a.unit_scale for a in head.actuators])
        self.solver = Solver(head, target_solvers)
        self.safety = SafetyFilter(head)
        self.timeline = Timeline()
        rt = self.cfg.runtime
        self.stream = JitterBuffer(rt.stream_delay_s, rt.stream_max_frames, rt.stream_max_ahead_s)
        self.period = 1.0 / rt.rate_hz
        self.stats = LoopStats(self.period)
        self.clock: Callable[[], float] = time.monotonic
        self.lifecycle = UNCONFIGURED
        self.mode = "hold"  # hold | clip | stream | pose | neutral
        self.pose_target: np.ndarray | None = None
        self.pose_speed = self.cfg.safety.safe_speed
        self.measured = np.full(len(self.names), np.nan)
        self.extra: dict[str, Any] = {}
        self.fault_info: dict[str, Any] | None = None
        self.estop_reason: str | None = None
        self.realtime_status = "not started"
        self.recorder: Recorder | None = None
        self.record_name: str | None = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=2000)
        self._threads: list[threading.Thread] = []
        self._ctx: zmq.Context | None = None
        self._auth: Any = None
        self._router: zmq.Socket | None = None
        self._pub: zmq.Socket | None = None
        self._rearm = False
        index = {n: i for i, n in enumerate(self.names)}
        self._bus_slices = [(bus, np.array([index[m] for m in bus.motors], dtype=int))
                            for bus in self.hw.buses.values()]
        self._bus_stamp = [0.0] * len(self._bus_slices)
        self._write_stamp = np.zeros(len(self.names))
        self._enabled_at = 0.0
        self._watchdog_stage = ""
        self._clip_done_reported = False
        self._pending_misses = 0
        self._last_miss_event = 0.0
        self._stats_cache: dict[str, Any] = {}
        self._stats_at = -1.0
        self._read_error_logged = False
        self._stamps: dict[str, float] = {}
        self._control_tid = 0
        self._caller_tid = 0
        self._promoted = False
        self.command_endpoint = ""
        self.telemetry_endpoint = ""
        self.loop_ready = threading.Event()

    # ================================================================== start / stop
    def start(self) -> None:
        """Open the buses, bind the sockets and start the control and API threads."""
        self._caller_tid = threading.get_native_id()
        self._promote(include_caller=True)  # opening emulated buses under load needs it too
        try:
            self.hw.open()
        finally:
            if self._promoted:
                drop_realtime()  # the caller's own work (a test, a demo client) stays at normal priority
        self._promote()
        try:
            self._bind()
            self.lifecycle = INACTIVE
            self._read_measured()
            self.safety.reset(self._measured_map())
            api = threading.Thread(target=self._serve_api, name="likeness-api", daemon=True)
            ctl = threading.Thread(target=self._run_loop, name="likeness-control", daemon=True)
            self._threads = [api, ctl]
            api.start()
            ctl.start()
            if not self.loop_ready.wait(10.0):
                raise RuntimeError("control loop did not start")
            self._event("lifecycle", state=INACTIVE, previous=UNCONFIGURED)
            if self.cfg.runtime.auto_enable:
                self.enable()
        except BaseException:
            self.stop()
            raise

    def _promote(self, include_caller: bool = False) -> None:
        """Helper threads (and in-process emulators) to realtime priority below the control thread's."""
        rt = self.cfg.runtime
        if rt.realtime and rt.helper_priority > 0:
            exclude = {self._control_tid} if self._control_tid else set()
            if not include_caller:
                exclude.add(self._caller_tid)
            n = promote_threads(rt.helper_priority, exclude)
            if n:
                self._promoted = True
                log.debug("%d helper threads now SCHED_FIFO %d", n, rt.helper_priority)

    def stop(self) -> None:
        """Stop serving, torque off, close buses and sockets; safe to call twice."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        with self._lock:
            if self.recorder is not None:
                self._finish_recording()
            try:
                self.hw.disable()
            except Exception:
                log.exception("disable on shutdown failed")
            self.hw.close()
            self.lifecycle = UNCONFIGURED
        for sock in (self._router, self._pub):
            if sock is not None:
                sock.close(0)
        self._router = self._pub = None
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _bind(self) -> None:
        api = self.cfg.api
        self._ctx = zmq.Context()
        router = self._ctx.socket(zmq.ROUTER)
        pub = self._ctx.socket(zmq.PUB)
        for sock in (router, pub):
            sock.setsockopt(zmq.LINGER, 0)
        router.setsockopt(zmq.MAXMSGSIZE, api.hard_max_message_bytes)
        router.setsockopt(zmq.ROUTER_MANDATORY, 0)
        router.setsockopt(zmq.SNDHWM, 1000)
        router.setsockopt(zmq.RCVHWM, 1000)
        pub.setsockopt(zmq.SNDHWM, 1000)
        if api.curve_secret_key:
            from zmq.auth import load_certificate
            from zmq.auth.thread import ThreadAuthenticator

            base = self.head.source.parent
            public, secret = load_certificate(str(resolve(base, api.curve_secret_key)))
            if secret is None:
                raise ValueError(f"api.curve_secret_key: {api.curve_secret_key} holds no secret key")
            self._auth = ThreadAuthenticator(self._ctx)
            self._auth.start()
            self._auth.configure_curve(domain="*", location=str(resolve(base, api.curve_allow_dir)))
            for sock in (router, pub):
                sock.curve_secretkey = secret
                sock.curve_publickey = public
                sock.curve_server = True
        router.bind(api.command)
        pub.bind(api.telemetry)
        self.command_endpoint = router.getsockopt_string(zmq.LAST_ENDPOINT)
        self.telemetry_endpoint = pub.getsockopt_string(zmq.LAST_ENDPOINT)
        self._router, self._pub = router, pub
        log.info("commands on %s, telemetry on %s%s", self.command_endpoint, self.telemetry_endpoint,
                 " (CURVE)" if api.curve_secret_key else "")

    # ================================================================== control loop
    def _run_loop(self) -> None:
        rt = self.cfg.runtime
        self._control_tid = threading.get_native_id()
        if rt.realtime:
            drop_realtime()
            ok, msg = try_realtime(rt.priority)
        else:
            ok, msg = False, "realtime priority disabled in config ([runtime] realtime = false)"
        self.realtime_status = msg
        (log.info if ok else log.warning)("%s", msg)
        freeze_heap()
        sched = RateScheduler(self.period, rt.spin_us * 1e-6, self.clock)
        tele_every = max(1, round(rt.rate_hz / rt.telemetry_hz))
        k = 0
        self.loop_ready.set()
        try:
            with SwitchInterval(rt.switch_interval_s):
                while not self._stop.is_set():
                    late, missed = sched.wait()
                    t0 = self.clock()
                    state_msg = None
                    read = self._read_hw()
                    with self._lock:
                        if missed:
                            self.stats.missed += missed
                            self._pending_misses += missed
                        self._cycle(t0, read)
                        k += 1
                        if k % tele_every == 0:
                            state_msg = self._state_message(t0)
                        if self._pending_misses and t0 - self._last_miss_event >= 1.0:
                            self._event("deadline_miss", count=self._pending_misses, total=self.stats.missed)
                            self._pending_misses = 0
                            self._last_miss_event = t0
                        rearm, self._rearm = self._rearm, False
                    self._publish(state_msg)
                    self.stats.add(late, self.clock() - t0, t0)
                    if rearm:
                        self.stats.skipped += 1
                        sched.rearm()
        except Exception:
            log.exception("control loop crashed; disabling torque")
            with self._lock:
                self._fault("control loop", "the control loop crashed (see log)")
            self._publish(None)
        finally:
            drop_realtime()

    def _cycle(self, now: float, read: tuple[Mapping[str, Any] | None, BusError | None]) -> None:
        """One control cycle (lock held) on the states ``read`` just before."""
        if self.lifecycle == UNCONFIGURED:
            return
        states_ok = self._read_measured(read)
        if self.lifecycle == ACTIVE:
            if not states_ok:
                return
            bad = [f"{b}: {s.value}" for b, s in self.hw.states.items() if s is not LifecycleState.ACTIVE]
            if bad:
                faults = self.hw.faults()
                self._fault("driver", "; ".join(f"{d}: 0x{c:04X} {m}" for d, (c, m) in faults.items()) or
                            ", ".join(bad), faults)
                return
            if now - self._enabled_at > self.cfg.safety.feedback_timeout_s:
                stale = [n for n, ts in self._stamps.items() if now - ts > self.cfg.safety.feedback_timeout_s]
                if stale:
                    self._fault("timeout", f"no fresh feedback for {self.cfg.safety.feedback_timeout_s:g} s from "
                                f"{', '.join(stale)}")
                    return
            targets, speed = self._desired(now)
            # Per-actuator time since its bus's previous write, stamped just before that write: a bus measures the
            # interval between its own writes, which is never shorter than this, so its rate guard always agrees.
            t_step = self.clock()
            dt = np.minimum(t_step - self._write_stamp, 4 * self.period)
            q = self.safety.step(targets, dt, speed)
            values = q.tolist()
            try:
                for b, (bus, idx) in enumerate(self._bus_slices):
                    self._bus_stamp[b] = self.clock()
                    bus.write({self.names[i]: values[i] for i in idx})
            except BusError as exc:
                self._fault("write", str(exc))
                return
            for b, (_, idx) in enumerate(self._bus_slices):
                self._write_stamp[idx] = self._bus_stamp[b]
        if self.recorder is not None:
            self.recorder.add(now, self.safety.q, self.measured)

    def _read_hw(self) -> tuple[Mapping[str, Any] | None, BusError | None]:
        """Read every bus (the buses lock themselves; the daemon lock is not needed, so the API is not held up)."""
        if self.lifecycle == UNCONFIGURED:
            return None, None
        try:
            return self.hw.read(), None
        except BusError as exc:
            return None, exc

    def _read_measured(self, result: tuple[Mapping[str, Any] | None, BusError | None] | None = None) -> bool:
        states, exc = result if result is not None else self._read_hw()
        if exc is not None or states is None:
            if self.lifecycle == ACTIVE:
                self._fault("read", str(exc))
            elif not self._read_error_logged:
                log.warning("read failed: %s", exc)
                self._read_error_logged = True
            return False
        self._read_error_logged = False
        idx = self.safety.index
        stamps = {}
        for n, s in states.items():
            i = idx.get(n)
            if i is not None:
                self.measured[i] = s.position
                stamps[n] = s.timestamp
        self._stamps = stamps
        return True

    def _measured_map(self) -> dict[str, float]:
        return {n: float(x) for n, x in zip(self.names, self.measured, strict=True) if math.isfinite(x)}

    def _desired(self, now: float) -> tuple[np.ndarray, float]:
        """Targets (SI, NaN = hold) and speed fraction for this cycle, from the active source."""
        mode = self.mode
        if mode == "clip":
            values = self.timeline.evaluate(now)
            if self.timeline.finished(now) and not self._clip_done_reported:
                self._clip_done_reported = True
                self._event("clip", state="finished", clip=self.timeline.playback.clip.name)  # type: ignore[union-attr]
            return self._solve(values), 1.0
        if mode == "stream":
            sf = self.cfg.safety
            age = self.stream.starved_for(now)
            if age > sf.watchdog_neutral_s:
                self._event("watchdog", stage="neutral", age=age)
                self._set_mode("neutral")
                self.stream.clear()
                return self.safety.neutral.copy(), sf.safe_speed
            if age > sf.watchdog_hold_s:
                if self._watchdog_stage != "hold":
                    self._watchdog_stage = "hold"
                    self._event("watchdog", stage="hold", age=age)
                return self._hold(), 1.0
            self._watchdog_stage = ""
            return self._solve(self.stream.evaluate(now)), 1.0
        if mode == "pose" and self.pose_target is not None:
            return self.pose_target, self.pose_speed
        if mode == "neutral":
            return self.safety.neutral.copy(), self.cfg.safety.safe_speed
        return self._hold(), 1.0

    def _hold(self) -> np.ndarray:
        return np.full(len(self.names), np.nan)

    def _solve(self, values: Mapping[str, float] | None) -> np.ndarray:
        if not values:
            return self._hold()
        res = self.solver.solve(values, self.safety.commands() if self.solver.target_solvers else {})
        if res.extra:
            self.extra = res.extra
        return self.safety.vector(res.actuators)

    # ================================================================== lifecycle transitions (lock held)
    def _set_lifecycle(self, state: str) -> None:
        if state != self.lifecycle:
            previous, self.lifecycle = self.lifecycle, state
            self._event("lifecycle", state=state, previous=previous)

    def _set_mode(self, mode: str) -> None:
        if mode != self.mode:
            self.mode = mode
            self._watchdog_stage = ""

    def _stop_motion(self) -> None:
        self._set_mode("hold")
        self.timeline.stop()
        self.stream.clear()
        self.pose_target = None

    def _fault(self, source: str, message: str, faults: Mapping[str, Any] | None = None) -> None:
        """Enter FAULT: stop commanding, torque off as configured, publish the event."""
        if self.lifecycle in (FAULT, ESTOP, UNCONFIGURED):
            return
        log.error("FAULT (%s): %s", source, message)
        self.fault_info = {"source": source, "message": message, "t": self.clock(),
                           "faults": {k: [c, m] for k, (c, m) in (faults or self.hw.faults()).items()}}
        self._stop_motion()
        self._set_lifecycle(FAULT)
        self._event("fault", **self.fault_info)
        if self.cfg.safety.fault_action == "disable":
            self._quiet_disable()

    def _quiet_disable(self) -> None:
        try:
            self.hw.disable()
        except Exception as exc:
            log.error("torque off failed: %s", exc)

    def enable(self) -> None:
        with self._lock:
            if self.lifecycle == ACTIVE:
                return
            self._require_ready()
            if self.lifecycle != INACTIVE:
                raise ProtocolError("bad_state", f"enable needs lifecycle inactive (is {self.lifecycle})")
            try:
                self.hw.enable()
            except BusError as exc:
                raise ProtocolError("hardware", f"enable failed: {exc}") from None
            self._read_measured()
            self.safety.reset(self._measured_map())
            self._enabled_at = self.clock()
            self._write_stamp[:] = self._enabled_at
            self._stop_motion()
            self._set_lifecycle(ACTIVE)
            self._rearm = True

    def disable(self) -> None:
        with self._lock:
            self._stop_motion()
            if self.lifecycle == ACTIVE:
                try:
                    self.hw.disable()
                except BusError as exc:
                    self._fault("disable", str(exc))
                    raise ProtocolError("hardware", f"disable failed: {exc}") from None
                self._set_lifecycle(INACTIVE)
            self._rearm = True

    def estop(self, reason: str = "api") -> None:
        """Latched emergency stop: stop commanding and (as configured) torque off until ``reset``."""
        with self._lock:
            if self.lifecycle == UNCONFIGURED:
                return
            self.estop_reason = reason
            self._stop_motion()
            if self.lifecycle != ESTOP:
                self._set_lifecycle(ESTOP)
                self._event("estop", reason=reason)
            if self.cfg.safety.estop_action == "disable":
                self._quiet_disable()
            self._rearm = True

    def reset(self) -> None:
        """Clear a latched e-stop or a fault: drivers reset, torque off, lifecycle inactive."""
        with self._lock:
            if self.lifecycle == UNCONFIGURED:
                raise ProtocolError("bad_state", "daemon is not running")
            self._stop_motion()
            try:
                self.hw.disable()
                self.hw.reset_fault()
            except BusError as exc:
                raise ProtocolError("hardware", f"reset failed: {exc}") from None
            finally:
                self._rearm = True
            if any(s is LifecycleState.FAULT for s in self.hw.states.values()):
                raise ProtocolError("fault", f"a bus is still in FAULT after reset: {self.hw.faults()}")
            self.fault_info = None
            self.estop_reason = None
            self._set_lifecycle(INACTIVE)

    def _require_ready(self) -> None:
        if self.lifecycle == ESTOP:
            raise ProtocolError("estop", f"e-stop is latched ({self.estop_reason}); send reset")
        if self.lifecycle == FAULT:
            msg = (self.fault_info or {}).get("message", "")
            raise ProtocolError("fault", f"head is in FAULT ({msg}); send reset")

    def _require_active(self, op: str) -> None:
        self._require_ready()
        if self.lifecycle != ACTIVE:
            raise ProtocolError("bad_state", f"{op} needs lifecycle active (is {self.lifecycle}); send enable")

    # ================================================================== telemetry
    def _event(self, kind: str, **data: Any) -> None:
        self._events.append({"event": kind, "t": self.clock(), **data})

    def _loop_summary(self, now: float) -> dict[str, Any]:
        if now - self._stats_at > 0.5:
            self._stats_cache = self.stats.summary()
            self._stats_at = now
        return self._stats_cache

    def _units(self, si: np.ndarray) -> dict[str, float | None]:
        vals = (si / self._scale).tolist()
        return {n: (v if math.isfinite(v) else None) for n, v in zip(self.names, vals, strict=True)}

    def _state_message(self, now: float) -> dict[str, Any]:
        msg = {
            "t": now, "lifecycle": self.lifecycle, "mode": self.mode,
            "commanded": self._units(self.safety.q), "measured": self._units(self.measured),
            "loop": self._loop_summary(now),
        }
        pb = self.timeline.playback
        if pb is not None:
            msg["clip"] = {"name": pb.clip.name, "time": self.timeline.clip_time(now), "duration": pb.clip.duration}
        if self.mode == "stream":
            msg["stream"] = self.stream.stats()
        if self.extra:
            msg["extra"] = self.extra
        return msg

    def _publish(self, state_msg: dict[str, Any] | None) -> None:
        pub = self._pub
        if pub is None:
            return
        try:
            while self._events:
                pub.send_multipart([P.TOPIC_EVENT, P.pack(self._events.popleft())], zmq.NOBLOCK)
            if state_msg is not None:
                pub.send_multipart([P.TOPIC_STATE, P.pack(state_msg)], zmq.NOBLOCK)
        except zmq.Again:
            pass
        except zmq.ZMQError as exc:
            log.warning("telemetry publish failed: %s", exc)

    # ================================================================== API
    def _serve_api(self) -> None:
        router = self._router
        assert router is not None
        poller = zmq.Poller()
        poller.register(router, zmq.POLLIN)
        limit = self.cfg.api.max_message_bytes
        next_promote = 0.0
        while not self._stop.is_set():
            if self.clock() > next_promote:  # threads created since (bus notifiers after a reset, ...)
                self._promote()
                next_promote = self.clock() + 2.0
            try:
                if not poller.poll(50):
                    continue
                frames = router.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                continue
            except zmq.ZMQError as exc:
                if self._stop.is_set():
                    break
                log.warning("command socket error: %s", exc)
                continue
            received = self.clock()
            if len(frames) < 2:
                continue
            envelope, payload = frames[:-1], frames[-1]
            if len(payload) > limit:
                reply = P.error_reply(None, "too_large", f"request of {len(payload)} bytes exceeds {limit} bytes")
            else:
                reply = self.handle_raw(payload, received)
            try:
                router.send_multipart([*envelope, P.pack(reply)], zmq.NOBLOCK)
            except zmq.ZMQError as exc:
                log.debug("reply not sent: %s", exc)

    def handle_raw(self, payload: bytes, received: float | None = None) -> dict[str, Any]:
        """Decode and handle one request; always returns a reply map, never raises."""
        try:
            msg = P.unpack(payload)
        except ProtocolError as exc:
            return P.error_reply(None, exc.code, exc.message)
        return self.handle(msg, received)

    def handle(self, msg: Any, received: float | None = None) -> dict[str, Any]:
        """Handle one decoded request; always returns a reply map, never raises."""
        rid = P.request_id(msg)
        received = self.clock() if received is None else received
        try:
            if not isinstance(msg, Mapping):
                raise ProtocolError("bad_request", "a request must be a map with 'op' and 'id'")
            op = msg.get("op")
            if not isinstance(op, str):
                raise ProtocolError("bad_request", "field 'op' must be a string")
            if "id" in msg and rid is None:
                raise ProtocolError("bad_request", "field 'id' must be an integer or a string of up to 128 chars")
            handler = self._OPS.get(op)
            if handler is None:
                raise ProtocolError("unknown_op", f"unknown op {op[:40]!r}; known: {', '.join(sorted(self._OPS))}")
            body = handler(self, msg, received)
            return {"id": rid, "ok": True, **body}
        except ProtocolError as exc:
            return P.error_reply(rid, exc.code, exc.message)
        except Exception as exc:  # a bug must never take the daemon down
            log.exception("internal error handling a request")
            return P.error_reply(rid, "internal", f"{type(exc).__name__}: {exc}")

    # ---------------------------------------------------------------- ops
    def _op_hello(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, {"client"})
        from likeness import __version__

        acts = []
        for a in self.head.actuators:
            s = a.unit_scale
            acts.append({"name": a.name, "unit": a.unit, "bus": a.bus, "min": a.min / s, "max": a.max / s,
                         "neutral": a.neutral / s, "max_velocity": a.max_velocity / s,
                         "max_acceleration": a.max_acceleration / s})
        groups = [{"name": g.name, "kind": g.kind, "actuators": list(g.actuators), "gains": list(g.gains)}
                  for g in self.head.groups]
        return {
            "protocol": P.PROTOCOL_VERSION, "daemon": f"likeness {__version__}",
            "head": {"name": self.head.name, "description": self.head.description, "actuators": acts,
                     "groups": groups, "channels": self.solver.channels()},
            "rate_hz": self.cfg.runtime.rate_hz, "telemetry": self.telemetry_endpoint,
            "ops": sorted(self._OPS), "max_message_bytes": self.cfg.api.max_message_bytes,
            "stream_delay_s": self.stream.delay,
        }

    def _op_status(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            now = self.clock()
            out = {
                "t": now, "lifecycle": self.lifecycle, "mode": self.mode, "estop": self.estop_reason,
                "fault": self.fault_info, "buses": {b: s.value for b, s in self.hw.states.items()},
                "commanded": self._units(self.safety.q), "measured": self._units(self.measured),
                "moving": bool(np.any(np.abs(self.safety.v) > 1e-4)),
                "loop": self.stats.summary(), "realtime": self.realtime_status,
                "timeline": self.timeline.describe(now), "stream": self.stream.stats(),
                "recording": None if self.recorder is None else {"name": self.record_name,
                                                                 "samples": self.recorder.count},
            }
            if self.mode == "pose" and self.pose_target is not None:
                err = np.abs(self.pose_target - self.safety.q)
                out["pose_reached"] = bool(np.all(err < 1e-6) and not out["moving"])
            if self.extra:
                out["extra"] = self.extra
        return out

    def _op_enable(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.enable()
        return {"lifecycle": self.lifecycle}

    def _op_disable(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.disable()
        return {"lifecycle": self.lifecycle}

    def _op_estop(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"reason"})
        self.estop(f.string("reason", "api", max_len=200))
        return {"lifecycle": self.lifecycle}

    def _op_reset(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        self.reset()
        return {"lifecycle": self.lifecycle}

    def _op_clock(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"t_client"})
        out: dict[str, Any] = {"t_recv": now, "clock": "monotonic"}
        if f.has("t_client"):
            out["t_client"] = f.number("t_client")
        out["t_send"] = self.clock()
        return out

    def _check_channels(self, channels: Iterable[str]) -> None:
        try:
            self.solver.check_channels(channels)
        except UnknownChannel as exc:
            raise ProtocolError("unknown_channel", f"unknown channel {str(exc.args[0])[:128]!r}; known: "
                                f"{', '.join(sorted(self.solver.channels()))}") from None

    def _op_load_clip(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"clip"})
        try:
            clip = clip_from_dict(f.mapping("clip"))
        except ClipError as exc:
            raise ProtocolError("bad_value", str(exc)) from None
        self._check_channels(clip.channels)
        with self._lock:
            try:
                self.timeline.load(clip)
            except ClipError as exc:
                raise ProtocolError("too_large", str(exc)) from None
        return {"clip": clip.name, "duration": clip.duration, "channels": sorted(clip.channels),
                "keys": clip.key_count()}

    def _op_play(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"clip", "at", "from", "speed", "loop"})
        name = f.string("clip")
        at = f.number("at", None, lo=now - 3600, hi=now + 3600) if f.has("at") else None
        offset = f.number("from", 0.0, lo=-3600, hi=86400)
        speed = f.number("speed", 1.0, lo=0.01, hi=10.0)
        loop = f.boolean("loop", False)
        with self._lock:
            self._require_active("play")
            if name not in self.timeline.clips:
                raise ProtocolError("not_found", f"no clip {name!r} loaded; loaded: {sorted(self.timeline.clips)}")
            self.stream.clear()
            start = self.timeline.play(name, self.clock(), at, offset, speed, loop)
            self._clip_done_reported = False
            self._set_mode("clip")
            self._event("clip", state="playing", clip=name, start=start)
            return {"clip": name, "start": start, "duration": self.timeline.clips[name].duration}

    def _op_pause(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._require_active("pause")
            self.timeline.pause(self.clock())
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_resume(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._require_active("resume")
            if self.timeline.playback is None:
                raise ProtocolError("bad_state", "nothing to resume: no clip is playing")
            self.timeline.resume(self.clock())
            self._set_mode("clip")
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_stop(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        Fields(msg, set())
        with self._lock:
            self._stop_motion()
        return {"mode": self.mode}

    def _op_seek(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"time"})
        t = f.number("time", lo=-3600, hi=86400)
        with self._lock:
            self._require_active("seek")
            if self.timeline.playback is None:
                raise ProtocolError("bad_state", "nothing to seek: no clip is playing")
            self.timeline.seek(self.clock(), t)
            return {"timeline": self.timeline.describe(self.clock())}

    def _op_stream(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"channels", "frames"})
        channels = f.array("channels", 256)
        if not channels or not all(isinstance(c, str) and 0 < len(c) <= 128 for c in channels):
            raise ProtocolError("bad_request", "field 'channels' must be a non-empty array of channel names")
        if len(set(channels)) != len(channels):
            raise ProtocolError("bad_request", "field 'channels' lists a channel twice")
        self._check_channels(channels)
        frames = f.array("frames", MAX_STREAM_FRAMES_PER_REQUEST)
        width = len(channels) + 1
        parsed: list[tuple[float, dict[str, float]]] = []
        for j, fr in enumerate(frames):
            if not isinstance(fr, list) or len(fr) != width:
                raise ProtocolError("bad_request", f"frames[{j}] must be [t, {len(channels)} values]")
            vals = [P.finite_number(x, f"frames[{j}][{k}]") for k, x in enumerate(fr)]
            parsed.append((vals[0], dict(zip(channels, vals[1:], strict=True))))
        with self._lock:
            self._require_active("stream")
            if self.mode != "stream":
                self.timeline.stop()
                self.stream.clear()
                self._set_mode("stream")
            now = self.clock()
            counts = {"ok": 0, "late": 0, "ahead": 0, "full": 0}
            for t, values in parsed:
                counts[self.stream.push(now, t, values)] += 1
            if counts["late"]:
                self._event("dropped_frames", late=counts["late"], total=self.stream.late)
            return {"accepted": counts["ok"], "late": counts["late"], "ahead": counts["ahead"],
                    "full": counts["full"], "buffered": len(self.stream), "t": now}

    def _op_pose(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"pose", "speed"})
        pose = f.mapping("pose")
        if not pose or len(pose) > 256:
            raise ProtocolError("bad_request", "field 'pose' must map 1..256 channels to values")
        values = {}
        for ch, v in pose.items():
            if not isinstance(ch, str):
                raise ProtocolError("bad_request", "pose channel names must be strings")
            values[ch] = P.finite_number(v, f"pose[{ch[:64]!r}]")
        self._check_channels(values)
        speed = f.number("speed", self.cfg.safety.safe_speed, lo=0.01, hi=1.0)
        with self._lock:
            self._require_active("pose")
            res = self.solver.solve(values, self.safety.commands())
            base = self.pose_target if self.mode == "pose" and self.pose_target is not None else self.safety.q
            x = self.safety.vector(res.actuators)
            target = self.safety.constrain(np.where(np.isfinite(x), x, base))
            self.timeline.stop()
            self.stream.clear()
            self.pose_target = target
            self.pose_speed = speed
            self._set_mode("pose")
            return {"targets": self._units(target), "speed": speed}

    def _op_record(self, msg: Mapping[str, Any], now: float) -> dict[str, Any]:
        f = Fields(msg, {"action", "name"})
        action = f.string("action")
        if action == "start":
            name = f.string("name", "recording", max_len=64)
            if not _RECORD_NAME.match(name):
                raise ProtocolError("bad_value", "record name: letters, digits, _ . - only (max 64)")
            rt = self.cfg.runtime
            capacity = int(rt.record_max_s * rt.rate_hz) + 1
            recorder = Recorder(self.names, self.units, self._scale, capacity,
                                {"head": self.head.name, "rate_hz": rt.rate_hz})
            with self._lock:
                if self.recorder is not None:
                    raise ProtocolError("bad_state", f"already recording {self.record_name!r}")
                self.recorder = recorder
                self.record_name = name
                self._event("record", state="started", name=name)
            return {"recording": name}
        if action == "stop":
            with self._lock:
                if self.recorder is None:
                    raise ProtocolError("bad_state", "not recording")
                return self._finish_recording()
        raise ProtocolError("bad_value", f"field 'action' must be 'start' or 'stop' (got {action[:32]!r})")

    def _finish_recording(self) -> dict[str, Any]:
        rec, name = self.recorder, self.record_name
        self.recorder = self.record_name = None
        assert rec is not None and name is not None
        path = Path(self.cfg.runtime.record_dir) / f"{name}.npz"
        rec.save(path)
        self._event("record", state="stopped", name=name, path=str(path), samples=rec.count)
        self._rearm = True
        return {"path": str(path.resolve()), "samples": rec.count, "dropped": rec.dropped}

    _OPS: ClassVar[dict[str, Callable[[Daemon, Mapping[str, Any], float], dict[str, Any]]]] = {
        "hello": _op_hello, "status": _op_status, "enable": _op_enable, "disable": _op_disable,
        "estop": _op_estop, "reset": _op_reset, "clock": _op_clock, "load_clip": _op_load_clip,
        "play": _op_play, "pause": _op_pause, "resume": _op_resume, "stop": _op_stop, "seek": _op_seek,
        "stream": _op_stream, "pose": _op_pose, "record": _op_record,
    }
