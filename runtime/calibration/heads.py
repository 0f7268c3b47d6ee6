"""Head drivers for calibration: move to a pose at a safe speed, wait until settled, report measured values.

- :class:`HardwareHead` drives a :class:`runtime.hardware.Hardware` directly (its own connection to the
  buses): a synchronised ramp within ``speed_fraction`` of each actuator's max velocity and acceleration,
  never outside the configured limits, then settles on encoder readings.
- :class:`DaemonHead` asks a running daemon to go to the pose (its ``pose`` op) and polls ``status``.
- :class:`KinematicHead` is the emulated mechanism with ideal motors (instant, exact): fast checks of the
  fitting path with no buses at all.
All values are SI and keyed by actuator name.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from typing import Protocol

import numpy as np

from drivers.errors import CommandRejected
from runtime.calibration.capture import CalibrationError


class HeadDriver(Protocol):
    """What the calibration needs from a head."""

    def move_to(self, pose: Mapping[str, float]) -> None: ...

    def wait_settled(self) -> None: ...

    def measured(self) -> dict[str, float]: ...

    def faults(self) -> list[str]: ...

    def close(self) -> None: ...


def _clamp(head, pose: Mapping[str, float]) -> dict[str, float]:
    """Every actuator's target, refusing unknown names and clamping to the configured limits."""
    out = {}
    for a in head.actuators:
        v = float(pose.get(a.name, a.neutral))
        if not math.isfinite(v):
            raise CalibrationError(f"pose value for {a.name!r} is not finite")
        out[a.name] = min(max(v, a.min), a.max)
    for name in pose:
        if name not in out:
            raise CalibrationError(f"pose names unknown actuator {name!r}")
    return out


class KinematicHead:
    """Ideal motors: positions jump to the (clamped) target; ``positions()`` feeds a simulated tracker."""

    def __init__(self, head) -> None:
        self.head = head
        self._pos = {a.name: a.neutral for a in head.actuators}

    def move_to(self, pose: Mapping[str, float]) -> None:
        self._pos = _clamp(self.head, pose)

    def wait_settled(self) -> None:
        pass

    def measured(self) -> dict[str, float]:
        return dict(self._pos)

    def positions(self) -> dict[str, float]:
        """Ground truth (the same as measured for ideal motors)."""
        return dict(self._pos)

    def faults(self) -> list[str]:
        return []

    def close(self) -> None:
        pass


class HardwareHead:
    """Calibration moves through :class:`runtime.hardware.Hardware` (opened and enabled here)."""

    def __init__(
        self,
        hardware,
        head,
        speed_fraction: float = 0.3,
        rate_hz: float = 100.0,
        tolerance: float = math.radians(0.3),
        settle_s: float = 0.05,
        timeout_s: float = 5.0,
    ) -> None:
        if not 0 < speed_fraction <= 1:
            raise ValueError("speed_fraction must be in (0, 1]")
        self.hw = hardware
        self.head = head
        self.speed_fraction = speed_fraction
        self.dt = 1.0 / rate_hz
        self.tolerance = tolerance
        self.settle_s = settle_s
        self.timeout_s = timeout_s
        self.names = tuple(head.actuator_names)
        self.lo = np.array([head.actuator(n).min for n in self.names])
        self.hi = np.array([head.actuator(n).max for n in self.names])
        self.vmax = np.array([head.actuator(n).max_velocity for n in self.names]) * speed_fraction
        self.amax = np.array([head.actuator(n).max_acceleration for n in self.names]) * speed_fraction
        groups: dict[str, list[int]] = {}
        for i, n in enumerate(self.names):
            groups.setdefault(head.actuator(n).bus, []).append(i)
        self._bus_groups = [np.array(v) for v in groups.values()]
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch, 0.0005))  # emulator threads must not stall the ramp for 5 ms
        self.hw.open()
        self.hw.enable()
        time.sleep(0.05)  # the drives hold where they are; first ramp steps stay within their rate guard
        self._target = self._read_vector()

    def _fresh_read(self, since: float | None = None, timeout_s: float = 1.0) -> dict:
        """Motor states all sampled after ``since`` (monotonic; default now): a bus whose last read failed
        reports its previous sample, which must not pass for the settled pose."""
        since = time.monotonic() if since is None else since
        deadline = time.monotonic() + timeout_s
        while True:
            states = self.hw.read()
            bad = [n for n, s in states.items() if s.fault]
            if bad:
                raise CalibrationError(f"drive fault on {', '.join(sorted(bad))}")
            stale = [n for n in self.names if states[n].timestamp < since]
            if not stale:
                return states
            if time.monotonic() > deadline:
                raise CalibrationError(f"no fresh feedback from {', '.join(stale)} within {timeout_s} s")
            time.sleep(0.002)

    def _read_vector(self) -> np.ndarray:
        states = self._fresh_read()
        return np.array([states[n].position for n in self.names])

    def move_to(self, pose: Mapping[str, float]) -> None:
        """Ramp every actuator to ``pose`` together, timed on the clock so no write outruns the speed limit."""
        target = np.array(list(_clamp(self.head, pose).values()))
        start = self._target
        dist = np.abs(target - start)
        # smoothstep over T peaks at 1.5·d/T speed and 6·d/T² acceleration: keep both within the fractions
        duration = float(np.max(np.maximum(1.5 * dist / self.vmax, np.sqrt(6.0 * dist / self.amax))))
        t0 = time.monotonic()
        while True:
            tick = time.monotonic()
            finished = True
            # each bus gets the ramp value of the moment it is written: a slow bus never makes the next one jump
            for idx in self._bus_groups:
                now = time.monotonic()
                s = 1.0 if duration <= 0 else min((now - t0) / duration, 1.0)
                finished = s >= 1.0
                s = s * s * (3.0 - 2.0 * s)  # smoothstep: zero velocity at both ends
                q = np.clip(start[idx] + (target[idx] - start[idx]) * s, self.lo[idx], self.hi[idx])
                self._write({self.names[i]: float(v) for i, v in zip(idx, q, strict=True)})
            if finished:
                break
            time.sleep(max(0.0, self.dt - (time.monotonic() - tick)))
        self._target = target

    def _write(self, targets: dict[str, float]) -> None:
        """Write one bus's targets. The driver's rate guard stamps a write when it gets the bus, so a thread
        switch between computing and writing can make a legal ramp step look too fast: such a refusal (and
        only that) is retried a moment later, when the elapsed time covers the step."""
        for attempt in range(20):
            try:
                self.hw.write(targets)
                return
            except CommandRejected as exc:
                if "exceeds max_velocity" not in str(exc) or attempt == 19:
                    raise
                time.sleep(0.002)

    def wait_settled(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        still_since = None
        while True:
            states = self._fresh_read(time.monotonic())
            pos = np.array([states[n].position for n in self.names])
            vel = np.array([states[n].velocity for n in self.names])
            ok = np.all(np.abs(pos - self._target) <= self.tolerance) and np.all(np.abs(vel) <= 5 * self.tolerance)
            now = time.monotonic()
            if ok:
                still_since = still_since or now
                if now - still_since >= self.settle_s:
                    return
            else:
                still_since = None
            if now > deadline:
                worst = self.names[int(np.argmax(np.abs(pos - self._target)))]
                raise CalibrationError(f"pose did not settle within {self.timeout_s} s (worst: {worst})")
            time.sleep(0.005)

    def measured(self) -> dict[str, float]:
        return dict(zip(self.names, self._read_vector().tolist(), strict=True))

    def recover(self) -> None:
        """After a drive fault (e.g. a following error at a hard stop): clear it, enable again, hold there."""
        self.hw.reset_fault()
        self.hw.enable()
        time.sleep(0.05)
        self._target = self._read_vector()

    def positions(self) -> dict[str, float]:
        """Ground truth of emulated motors (emulator side), for the simulated tracker."""
        return self.hw.simulated_positions()

    def faults(self) -> list[str]:
        return [f"{k}: {v}" for k, v in self.hw.faults().items()]

    def close(self) -> None:
        try:
            self.hw.disable()
        finally:
            self.hw.close()
            sys.setswitchinterval(self._switch)


class DaemonHead:
    """Calibration moves through a running daemon's API (protocol v1, ``docs/protocol.md``).

    Poses go out with the ``pose`` op at ``speed_fraction`` of max velocity (the daemon clips and rate-limits
    them again); ``status`` is polled until ``pose_reached``. The wire uses config units (degrees), converted
    here from and to SI. The daemon is enabled if it is inactive and left active, holding, at the end.
    """

    def __init__(
        self,
        endpoint: str,
        head,
        speed_fraction: float = 0.3,
        timeout_s: float = 15.0,
        tolerance: float = math.radians(0.3),
        settle_s: float = 0.05,
    ) -> None:
        from models.client import Client, DaemonError

        self.tolerance = tolerance
        self.settle_s = settle_s
        self._target: dict[str, float] = {}
        self.endpoint = endpoint
        self.head = head
        self.speed_fraction = speed_fraction
        self.timeout_s = timeout_s
        self._error = DaemonError
        self._client = Client(endpoint, timeout=5.0)
        try:
            st = self._call("status")
            if st.get("lifecycle") == "inactive":
                self._call("enable")
            elif st.get("lifecycle") != "active":
                raise CalibrationError(f"daemon at {endpoint} is {st.get('lifecycle')!r}; reset it first")
        except BaseException:
            self._client.close()
            raise

    def _call(self, op: str, **fields) -> dict:
        try:
            return self._client.call(op, **fields)
        except self._error as exc:
            raise CalibrationError(f"daemon at {self.endpoint} refused {op!r}: {exc}") from exc
        except TimeoutError as exc:
            raise CalibrationError(f"daemon at {self.endpoint} did not answer {op!r}") from exc

    def move_to(self, pose: Mapping[str, float]) -> None:
        target = _clamp(self.head, pose)
        values = {n: self.head.actuator(n).to_config_units(v) for n, v in target.items()}
        reply = self._call("pose", pose=values, speed=self.speed_fraction)
        # the daemon applies group constraints (e.g. lids "together"): settle on what it actually commands
        for name, value in dict(reply.get("targets") or {}).items():
            if name in target and value is not None:
                target[name] = self.head.actuator(name).from_config_units(float(value))
        self._target = target

    def wait_settled(self) -> None:
        """Until the daemon reports the command at the pose and the measured positions sit within
        ``tolerance`` of it for ``settle_s`` (``pose_reached`` alone says the command arrived, not the motors)."""
        deadline = time.monotonic() + self.timeout_s
        still_since = None
        worst = ""
        while time.monotonic() < deadline:
            st = self._call("status")
            if st.get("fault") or st.get("lifecycle") != "active":
                raise CalibrationError(f"daemon left active while moving: {st.get('lifecycle')} {st.get('fault')}")
            ok = bool(st.get("pose_reached"))
            if not ok and st.get("pose_settled"):
                # the skin-strain guard stopped it short of the plan's pose: calibrate where the head really is
                commanded = st.get("commanded") or {}
                self._target = {n: self.head.actuator(n).from_config_units(float(commanded[n]))
                                for n in self._target if commanded.get(n) is not None}
                ok = True
            if ok:
                measured = st.get("measured") or {}
                for name, target in self._target.items():
                    value = measured.get(name)
                    act = self.head.actuator(name)
                    if value is None or abs(act.from_config_units(float(value)) - target) > self.tolerance:
                        ok = False
                        worst = f"{name} at {value} {act.unit}, target {act.to_config_units(target):.2f}"
                        break
            else:
                worst = "pose_reached not reported"
            now = time.monotonic()
            if ok:
                still_since = still_since or now
                if now - still_since >= self.settle_s:
                    return
            else:
                still_since = None
            time.sleep(0.01)
        raise CalibrationError(f"daemon did not settle at the pose within {self.timeout_s} s ({worst})")

    def commanded(self) -> dict[str, float]:
        """The pose last commanded (SI): the plan's, or where the daemon's safety stage stopped it."""
        return dict(self._target)

    def measured(self) -> dict[str, float]:
        st = self._call("status")
        out = {}
        for name, value in dict(st.get("measured") or {}).items():
            if value is None:
                raise CalibrationError(f"daemon has no feedback from {name!r}")
            out[name] = self.head.actuator(name).from_config_units(float(value))
        return out

    def recover(self) -> None:
        """After a fault: ``reset`` the daemon and enable it again."""
        self._call("reset")
        self._call("enable")

    def positions(self) -> dict[str, float]:
        """For a simulated tracker without access to the emulators: the daemon's measured positions."""
        return self.measured()

    def faults(self) -> list[str]:
        st = self._call("status")
        return [str(st["fault"])] if st.get("fault") else []

    def close(self) -> None:
        self._client.close()
