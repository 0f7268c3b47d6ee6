"""The realtime daemon: lifecycle, the fixed-rate control loop and the ZeroMQ command and telemetry sockets.

Each cycle: read drivers → evaluate the timeline (clip, stream jitter buffer, pose, neutral) at show time → solve
channels to actuator targets → safety (limits, groups, rate shaping) → write drivers → record → publish telemetry.
The control thread owns the PUB socket; the API thread owns the ROUTER socket and changes state under one lock that
the control thread also takes for each cycle. Lifecycle (after ros2_control): inactive (buses open, torque off) →
active (commanding) → fault (stop commanding; torque off as configured) or estop (latched); ``reset`` → inactive.

Scheduling: the control thread asks for SCHED_FIFO (``[runtime] priority``) and every other thread of the process
(API, bus notifiers, in-process emulators, the caller) is raised to SCHED_RR: with a GIL, any normal-priority thread
preempted by other programs while holding it would stall the control thread. In-process emulators stand in for
devices that never wait for the host, so heads that use them rank helpers above the control thread.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import zmq

from drivers.base import LifecycleState
from drivers.errors import BusError
from models.headspec import HeadSpec
from models.linkmap import LinkMap
from models.rigid import matrix_to_rotvec
from runtime import protocol as P
from runtime.api import CommandApi
from runtime.config import DaemonConfig, daemon_config, resolve
from runtime.hardware import Hardware
from runtime.loop import (
    LoopStats,
    RateScheduler,
    SwitchInterval,
    demote_threads,
    drop_realtime,
    freeze_heap,
    promote_threads,
    try_realtime,
)
from runtime.protocol import ProtocolError
from runtime.recording import Recorder
from runtime.safety import SafetyFilter
from runtime.solve import Solver, TargetSolver
from runtime.timeline import JitterBuffer, Timeline

log = logging.getLogger(__name__)

INACTIVE, ACTIVE, FAULT, ESTOP, UNCONFIGURED = "inactive", "active", "fault", "estop", "unconfigured"


class Daemon(CommandApi):
    """One head's daemon. ``start()`` opens the buses and serves; ``stop()`` disables torque and closes everything."""

    def __init__(
        self,
        head: HeadSpec,
        overrides: Mapping[str, Any] | None = None,
        hardware: Hardware | None = None,
        target_solvers: Iterable[TargetSolver] | None = None,
    ) -> None:
        self.head = head
        self.cfg: DaemonConfig = daemon_config(head, overrides)
        self.hw = hardware if hardware is not None else Hardware.from_head(head)
        self.names = head.actuator_names
        self.units = [a.unit for a in head.actuators]
        self._scale = np.array([a.unit_scale for a in head.actuators])
        if target_solvers is None:  # from the head config: the skin solver when paths.predictor exists
            from runtime.skin import default_target_solvers

            target_solvers = default_target_solvers(head)
        self.solver = Solver(head, target_solvers)
        self.safety = SafetyFilter(head)
        self.linkmap = _load_linkmap(head)
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
        self._caller_sched: tuple[int, int] | None = None
        self._promoted_tids: list[int] = []
        self.command_endpoint = ""
        self.telemetry_endpoint = ""
        self.loop_ready = threading.Event()

    # ================================================================== start / stop
    def start(self) -> None:
        """Open the buses, bind the sockets and start the control and API threads."""
        self._caller_tid = threading.get_native_id()
        self._promote_caller()
        self._promote()  # in-process emulators, bus notifiers
        self.hw.open()
        self._promote()  # threads the drivers started while opening
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

    def _promote(self) -> None:
        """Helper threads (and in-process emulators) to realtime priority below the control thread's."""
        rt = self.cfg.runtime
        if rt.realtime and rt.helper_priority > 0:
            exclude = {t for t in (self._control_tid, self._caller_tid) if t}
            changed = promote_threads(rt.helper_priority, exclude)
            if changed:
                self._promoted_tids.extend(changed)
                log.debug("%d helper threads now SCHED_RR %d", len(changed), rt.helper_priority)

    def _promote_caller(self) -> None:
        """The thread that starts the daemon (a CLI's main thread, a test, a demo client) to the lowest realtime
        priority of the process. With a GIL, a normal-priority thread preempted by other programs while holding it
        stalls every realtime thread of the process (seen as 300 ms freezes on a loaded host)."""
        rt = self.cfg.runtime
        if not (rt.realtime and rt.helper_priority > 0) or not hasattr(os, "sched_getscheduler"):
            return
        try:
            before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            if before[0] == os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(max(1, min(rt.helper_priority, rt.priority) - 10)))
                self._caller_sched = before
        except OSError:
            pass

    def _restore_caller(self) -> None:
        if self._caller_sched is not None:
            policy, prio = self._caller_sched
            with contextlib.suppress(OSError):
                os.sched_setscheduler(self._caller_tid, policy, os.sched_param(prio))
            self._caller_sched = None

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
        self._restore_caller()
        demote_threads(self._promoted_tids)  # threads that outlive the daemon (a shared ZeroMQ context's, ...)
        self._promoted_tids = []

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
                        try:
                            self._cycle(t0, read)
                        except Exception as exc:  # a bug in one cycle: safe state, keep the loop alive
                            if self.lifecycle not in (FAULT, ESTOP):
                                log.exception("control cycle failed; entering FAULT")
                            self._fault("control loop", f"control cycle failed: {type(exc).__name__}: {exc}")
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
        if self.linkmap is not None and np.isfinite(self.measured).all():
            msg["links"] = self._link_poses(self.measured)
        return msg

    def _link_poses(self, q: np.ndarray) -> dict[str, list[float]]:
        """Predicted link poses m(q) at measured actuator values: [x, y, z (m), rx, ry, rz (rotation vector, rad)]."""
        poses = self.linkmap.poses(dict(zip(self.names, q.tolist(), strict=True)))
        return {name: [*T[:3, 3].tolist(), *matrix_to_rotvec(T[:3, :3]).tolist()] for name, T in poses.items()}

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


def _load_linkmap(head: HeadSpec) -> LinkMap | None:
    """The head's calibrated link map m(p) when its file exists (a map that does not match the head is refused)."""
    path = head.path("linkmap")
    if path is None:
        return None
    if not path.exists():
        log.warning("link map %s not found: telemetry carries no predicted link poses (run likeness calibrate)", path)
        return None
    return LinkMap.for_head(head)
