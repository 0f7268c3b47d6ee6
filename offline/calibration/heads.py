"""Head drivers for calibration: move to a pose at a safe speed, wait until settled, report measured values.

- :class:`DaemonHead` asks a daemon to go to the pose (its ``pose`` op) and polls ``status`` until the measured
  positions settle (:func:`wait_settled`). The daemon owns the buses (real or emulated), their limits and rates.
- :class:`KinematicHead` is ideal motors (instant, exact), optionally shown to a simulated tracker process: fast
  checks of the fitting path with no buses at all.
All values are SI and keyed by actuator name.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from models.headspec import HeadSpec
from offline.calibration.capture import CalibrationError


class HeadDriver(Protocol):
    """What the calibration needs from a head."""

    def move_to(self, pose: Mapping[str, float]) -> None: ...

    def wait_settled(self) -> None: ...

    def measured(self) -> dict[str, float]: ...

    def faults(self) -> list[str]: ...

    def close(self) -> None: ...


def _clamp(head: HeadSpec, pose: Mapping[str, float]) -> dict[str, float]:
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


def wait_settled(check: Callable[[], str], timeout_s: float, settle_s: float, poll_s: float,
                 what: str = "pose") -> None:
    """Poll ``check`` (returns ``""`` when the head is at the pose, else what is still off) until it has held for
    ``settle_s``; a :class:`CalibrationError` naming the last complaint after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    still_since: float | None = None
    worst = ""
    while time.monotonic() < deadline:
        worst = check()
        now = time.monotonic()
        if not worst:
            still_since = still_since or now
            if now - still_since >= settle_s:
                return
        else:
            still_since = None
        time.sleep(poll_s)
    raise CalibrationError(f"{what} did not settle at the pose within {timeout_s} s ({worst})")


class KinematicHead:
    """Ideal motors: positions jump to the (clamped) target. ``positions()`` feeds an in-process simulated
    tracker; ``show`` (e.g. :meth:`offline.calibration.processes.SimTrackerProcess.show`) is told every move."""

    def __init__(self, head: HeadSpec, show: Callable[[Mapping[str, float]], None] | None = None) -> None:
        self.head = head
        self.show = show
        self._pos = {a.name: a.neutral for a in head.actuators}

    def move_to(self, pose: Mapping[str, float]) -> None:
        self._pos = _clamp(self.head, pose)
        if self.show is not None:
            self.show(self._pos)

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


class DaemonHead:
    """Calibration moves through a running daemon's API (protocol v1, ``docs/protocol.md``).

    Poses go out with the ``pose`` op at ``speed_fraction`` of max velocity (the daemon clips and rate-limits
    them again); ``status`` is polled until ``pose_reached``. The wire uses config units (degrees), converted
    here from and to SI. The daemon is enabled if it is inactive and left active, holding, at the end. A daemon
    started for the run (``reset_start_fault``) that faulted before the first move (torque off, e.g. an emulated
    bus late on a loaded host) is reset first; any other daemon in fault or e-stop is left to the operator.
    """

    def __init__(
        self,
        endpoint: str,
        head: HeadSpec,
        speed_fraction: float = 0.3,
        timeout_s: float = 15.0,
        tolerance: float = math.radians(0.3),
        settle_s: float = 0.05,
        reset_start_fault: bool = False,
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
            if reset_start_fault and st.get("lifecycle") == "fault":
                self._call("reset")
                st = self._call("status")
            if st.get("lifecycle") == "inactive":
                self._call("enable")
            elif st.get("lifecycle") != "active":
                raise CalibrationError(f"daemon at {endpoint} is {st.get('lifecycle')!r}; reset it first")
        except BaseException:
            self._client.close()
            raise

    def _call(self, op: str, **fields: Any) -> dict[str, Any]:
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
        wait_settled(self._off_pose, self.timeout_s, self.settle_s, 0.01, "daemon")

    def _off_pose(self) -> str:
        """``""`` when the daemon holds the pose and every measured position is on target, else what is off."""
        st = self._call("status")
        if st.get("fault") or st.get("lifecycle") != "active":
            raise CalibrationError(f"daemon left active while moving: {st.get('lifecycle')} {st.get('fault')}")
        if not st.get("pose_reached"):
            if not st.get("pose_settled"):
                return "pose_reached not reported"
            # the skin-strain guard stopped it short of the plan's pose: calibrate where the head really is
            commanded = st.get("commanded") or {}
            self._target = {n: self.head.actuator(n).from_config_units(float(commanded[n]))
                            for n in self._target if commanded.get(n) is not None}
        measured = st.get("measured") or {}
        for name, target in self._target.items():
            value = measured.get(name)
            act = self.head.actuator(name)
            if value is None or abs(act.from_config_units(float(value)) - target) > self.tolerance:
                return f"{name} at {value} {act.unit}, target {act.to_config_units(target):.2f}"
        return ""

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

    def faults(self) -> list[str]:
        st = self._call("status")
        return [str(st["fault"])] if st.get("fault") else []

    def close(self) -> None:
        self._client.close()
