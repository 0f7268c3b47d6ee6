"""The ``MotorBus`` ABC: lifecycle, unit conversion and command guards shared by every backend.

Public methods enforce the lifecycle (unconfigured → inactive → active, any → fault) and refuse
commands outside each motor's configured position and velocity limits (a motor enabled where it stood outside its
position limits may only be commanded back toward them); backends implement the
``_``-prefixed hooks and only ever see commands that passed those checks. Positions are SI at this
interface (radians for rotary axes, metres for linear ones); encoder counts exist only in backends.
"""

from __future__ import annotations

import abc
import enum
import logging
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal, TypeAlias

from drivers.errors import CommandRejected, ConfigError, DeviceFault, LifecycleError

log = logging.getLogger(__name__)

#: A value of a bus's driver options as the head config gives it (a TOML value).
OptionValue: TypeAlias = "str | int | float | bool | Sequence[OptionValue] | Mapping[str, OptionValue]"


def _toward_range(motor: MotorConfig, target: float, last: tuple[float, float] | None) -> bool:
    """Whether ``target``, outside the motor's limits, is a move back toward them (or a hold) from its last command
    ``last`` (position, stamp) outside them on the same side: a motor found outside its limits (enabled where it
    stood) may only be brought back, never sent further out."""
    if last is None:
        return False
    if target < motor.min_position:
        return last[0] <= target
    return last[0] >= target


class LifecycleState(enum.Enum):
    """Lifecycle of a bus, after ros2_control's hardware components."""

    UNCONFIGURED = "unconfigured"  # closed: no communication
    INACTIVE = "inactive"  # communicating, torque off
    ACTIVE = "active"  # torque on, accepting position targets
    FAULT = "fault"  # a device faulted: no commands until reset_fault()


@dataclass(frozen=True, slots=True)
class MotorConfig:
    """One motor on a bus: its device id, encoder scaling and hard limits (SI units).

    ``counts_per_unit`` is encoder counts per output radian (rotary) or metre (linear), signed
    by the mounting direction; ``zero_count`` is the count at output position 0.
    """

    name: str
    device_id: int
    counts_per_unit: float
    min_position: float
    max_position: float
    max_velocity: float
    zero_count: int = 0
    kind: Literal["rotary", "linear"] = "rotary"
    options: Mapping[str, OptionValue] = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = f"motor {self.name!r}"
        if not self.name or not isinstance(self.name, str):
            raise ConfigError("name", f"must be a non-empty string, got {self.name!r}")
        if not isinstance(self.device_id, int) or isinstance(self.device_id, bool) or self.device_id < 0:
            raise ConfigError(f"{where}.device_id", f"must be a non-negative integer, got {self.device_id!r}")
        for key in ("counts_per_unit", "min_position", "max_position", "max_velocity"):
            value = getattr(self, key)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{where}.{key}", f"must be a finite number, got {value!r}")
        if self.counts_per_unit == 0:
            raise ConfigError(f"{where}.counts_per_unit", "must not be zero")
        if self.min_position >= self.max_position:
            raise ConfigError(
                f"{where}.min_position",
                f"must be below max_position ({self.min_position!r} >= {self.max_position!r})",
            )
        if self.max_velocity <= 0:
            raise ConfigError(f"{where}.max_velocity", f"must be positive, got {self.max_velocity!r}")
        if self.kind not in ("rotary", "linear"):
            raise ConfigError(f"{where}.kind", f"must be 'rotary' or 'linear', got {self.kind!r}")

    @classmethod
    def rotary(
        cls,
        name: str,
        device_id: int,
        *,
        counts_per_rev: int,
        min_position: float,
        max_position: float,
        max_velocity: float,
        gear_ratio: float = 1.0,
        direction: int = 1,
        zero_count: int = 0,
        options: Mapping[str, OptionValue] | None = None,
    ) -> MotorConfig:
        """A rotary axis: ``counts_per_rev`` at the motor, ``gear_ratio`` motor turns per output turn."""
        if direction not in (1, -1):
            raise ConfigError(f"motor {name!r}.direction", f"must be 1 or -1, got {direction!r}")
        if counts_per_rev <= 0:
            raise ConfigError(f"motor {name!r}.counts_per_rev", f"must be positive, got {counts_per_rev!r}")
        if not gear_ratio > 0:
            raise ConfigError(f"motor {name!r}.gear_ratio", f"must be positive, got {gear_ratio!r}")
        return cls(
            name=name,
            device_id=device_id,
            counts_per_unit=direction * counts_per_rev * gear_ratio / (2.0 * math.pi),
            min_position=min_position,
            max_position=max_position,
            max_velocity=max_velocity,
            zero_count=zero_count,
            kind="rotary",
            options=dict(options or {}),
        )

    def to_counts(self, position: float) -> int:
        """Output position (SI) → encoder count."""
        return round(self.zero_count + position * self.counts_per_unit)

    def from_counts(self, counts: int | float) -> float:
        """Encoder count → output position (SI)."""
        return (counts - self.zero_count) / self.counts_per_unit

    def velocity_to_counts(self, velocity: float) -> float:
        """Output velocity (SI/s) → counts per second."""
        return velocity * self.counts_per_unit

    def velocity_from_counts(self, counts_per_s: float) -> float:
        """Counts per second → output velocity (SI/s)."""
        return counts_per_s / self.counts_per_unit


@dataclass(frozen=True, slots=True)
class MotorState:
    """What one read reports for one motor (SI units; effort in amperes of motor current)."""

    position: float
    velocity: float
    effort: float
    status: int  # raw device status word / flags
    fault_code: int  # 0 when healthy; device-specific otherwise
    enabled: bool  # torque on
    timestamp: float  # time.monotonic() when the sample was taken

    @property
    def fault(self) -> bool:
        return self.fault_code != 0


class MotorBus(abc.ABC):
    """A bus of motors with a lifecycle; backends implement the ``_`` hooks.

    Thread safety: public methods take one lock, so a control thread and a supervising thread
    (for example a heartbeat monitor calling :meth:`mark_fault`) can share a bus.
    """

    driver_name: ClassVar[str] = ""
    #: Factor of slack on the velocity guard, to absorb loop jitter.
    RATE_TOLERANCE: ClassVar[float] = 1.5

    def __init__(self, name: str, options: Mapping[str, OptionValue], motors: Sequence[MotorConfig]) -> None:
        self.name = name
        self.options = dict(options)
        self._motors: dict[str, MotorConfig] = {}
        ids: dict[int, str] = {}
        for motor in motors:
            if motor.name in self._motors:
                raise ConfigError(f"bus {name!r}.motors", f"duplicate motor name {motor.name!r}")
            if motor.device_id in ids:
                raise ConfigError(
                    f"bus {name!r}.motors",
                    f"duplicate device id {motor.device_id} ({ids[motor.device_id]!r} and {motor.name!r})",
                )
            ids[motor.device_id] = motor.name
            self._motors[motor.name] = motor
        if not self._motors:
            raise ConfigError(f"bus {name!r}.motors", "a bus needs at least one motor")
        self._state = LifecycleState.UNCONFIGURED
        self._lock = threading.RLock()
        self._faults: dict[str, tuple[int, str]] = {}
        self._last_command: dict[str, tuple[float, float]] = {}  # name -> (position, monotonic time)
        self._holding: set[str] = set()  # motors still at the hold enable set up (no target written since)

    # ------------------------------------------------------------------ introspection
    @property
    def state(self) -> LifecycleState:
        return self._state

    @property
    def motors(self) -> Mapping[str, MotorConfig]:
        return self._motors

    def faults(self) -> dict[str, tuple[int, str]]:
        """Active faults by motor name (or the bus name for bus-wide faults): (code, message)."""
        with self._lock:
            return dict(self._faults)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Start communicating with every device (torque stays off): unconfigured → inactive."""
        with self._lock:
            self._require(LifecycleState.UNCONFIGURED, "open")
            self._open()
            self._faults.clear()  # a freshly opened bus starts without the faults of an earlier connection
            self._state = LifecycleState.INACTIVE
            log.info("bus %s (%s) open with %d motors", self.name, self.driver_name, len(self._motors))

    def close(self) -> None:
        """Disable torque where possible and stop communicating: any state → unconfigured."""
        with self._lock:
            if self._state is LifecycleState.UNCONFIGURED:
                return
            try:
                if self._state is LifecycleState.ACTIVE:
                    self._disable()
            finally:
                self._close()
                self._state = LifecycleState.UNCONFIGURED
                self._last_command.clear()

    def enable(self) -> None:
        """Torque on and hold the present position: inactive → active."""
        with self._lock:
            self._require(LifecycleState.INACTIVE, "enable")
            self._enable()
            now = time.monotonic()
            states = self._read()
            if self._faults:  # a fault seen while enabling wins: stay in FAULT, torque handled by _on_fault
                self._state = LifecycleState.FAULT
                device, (code, message) = next(iter(self._faults.items()))
                raise DeviceFault(device, code, f"fault while enabling bus {self.name!r}: {message}")
            self._last_command = {n: (s.position, now) for n, s in states.items()}
            self._holding = set(self._last_command)  # until each motor's first written target
            self._state = LifecycleState.ACTIVE

    def last_commands(self) -> dict[str, float]:
        """Each motor's last commanded position (SI): right after :meth:`enable`, the position it holds. The rate
        check measures the next target against it, so a controller starts commanding from here."""
        with self._lock:
            return {name: position for name, (position, _) in self._last_command.items()}

    def disable(self) -> None:
        """Torque off: active → inactive (a no-op when already inactive)."""
        with self._lock:
            if self._state is LifecycleState.INACTIVE:
                return
            self._require(LifecycleState.ACTIVE, "disable")
            self._disable()
            self._state = LifecycleState.INACTIVE
            self._last_command.clear()

    def reset_fault(self) -> None:
        """Clear device faults and return to inactive (torque off): fault → inactive."""
        with self._lock:
            self._require(LifecycleState.FAULT, "reset_fault")
            self._reset_fault()
            self._faults.clear()
            self._state = LifecycleState.INACTIVE

    def mark_fault(self, device: str, code: int, message: str) -> None:
        """Record a fault and enter FAULT, stopping commands (backends and monitors call this)."""
        with self._lock:
            first = self._state is not LifecycleState.FAULT
            self._faults[device] = (code, message)
            if self._state is LifecycleState.UNCONFIGURED:
                return
            self._state = LifecycleState.FAULT
            self._last_command.clear()
            if first:
                log.error("bus %s fault on %s: 0x%04X %s", self.name, device, code, message)
                try:
                    self._on_fault()
                except Exception:  # the safe-state hook must never mask the fault itself
                    log.exception("bus %s: safe-state action after fault failed", self.name)

    # ------------------------------------------------------------------ cyclic I/O
    def read(self) -> dict[str, MotorState]:
        """Latest state of every motor; allowed while inactive, active or faulted."""
        with self._lock:
            if self._state is LifecycleState.UNCONFIGURED:
                raise LifecycleError(f"bus {self.name!r}: read needs an open bus (state is unconfigured)")
            return self._read()

    def write(self, targets: Mapping[str, float], stamp: float | None = None) -> None:
        """Command position targets (SI) for some or all motors; refused unless every check passes.

        ``stamp`` (``time.monotonic()``) is when the targets were computed, for the rate check; default now. A caller
        that hands targets over to another thread or process passes it, so a delay in the hand-over never makes a
        legal step look too fast (nor a fast one legal).
        """
        with self._lock:
            if self._state is LifecycleState.FAULT:
                device, (code, message) = next(iter(self._faults.items()), (self.name, (0, "fault")))
                raise DeviceFault(device, code, f"bus {self.name!r} is in FAULT ({message})")
            self._require(LifecycleState.ACTIVE, "write")
            now = time.monotonic() if stamp is None else float(stamp)
            checked: dict[str, float] = {}
            for name, value in targets.items():
                motor = self._motors.get(name)
                if motor is None:
                    raise CommandRejected(f"bus {self.name!r}: unknown motor {name!r}")
                try:
                    target = float(value)
                except (TypeError, ValueError):
                    raise CommandRejected(f"{name}: target {value!r} is not a number") from None
                if not math.isfinite(target):
                    raise CommandRejected(f"{name}: target {target!r} is not finite")
                last = self._last_command.get(name)
                if not motor.min_position <= target <= motor.max_position and not _toward_range(motor, target, last):
                    raise CommandRejected(
                        f"{name}: target {target:.6g} outside [{motor.min_position:.6g}, {motor.max_position:.6g}]"
                        + ("" if last is None else f" and not toward it from {last[0]:.6g}")
                    )
                if last is not None:
                    dt = now - last[1]
                    if name in self._holding and dt < 0:
                        # Targets computed before the hold that enable set up (the caller could not see it yet):
                        # the time that has really passed since that hold is what the motor had.
                        dt = time.monotonic() - last[1]
                    dt = max(dt, 1e-3)
                    allowed = motor.max_velocity * dt * self.RATE_TOLERANCE + 1e-9
                    if abs(target - last[0]) > allowed:
                        raise CommandRejected(
                            f"{name}: step {target - last[0]:.6g} in {dt * 1e3:.2f} ms exceeds max_velocity "
                            f"{motor.max_velocity:.6g}/s"
                        )
                checked[name] = target
            self._write(checked)
            for name, target in checked.items():
                self._last_command[name] = (target, now)
                self._holding.discard(name)

    # ------------------------------------------------------------------ helpers
    def _require(self, expected: LifecycleState, operation: str) -> None:
        if self._state is not expected:
            raise LifecycleError(
                f"bus {self.name!r}: {operation} needs state {expected.value}, state is {self._state.value}"
            )

    def __enter__(self) -> MotorBus:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ backend hooks
    @abc.abstractmethod
    def _open(self) -> None:
        """Connect, find every device (raise BusTimeout naming a silent one), configure, torque off."""

    @abc.abstractmethod
    def _close(self) -> None:
        """Release the bus; must not raise for an already broken connection."""

    @abc.abstractmethod
    def _enable(self) -> None:
        """Torque on, holding the present position."""

    @abc.abstractmethod
    def _disable(self) -> None:
        """Torque off."""

    @abc.abstractmethod
    def _write(self, targets: Mapping[str, float]) -> None:
        """Send checked position targets (SI)."""

    @abc.abstractmethod
    def _read(self) -> dict[str, MotorState]:
        """Return the latest state of every motor; call :meth:`mark_fault` for faults seen."""

    @abc.abstractmethod
    def _reset_fault(self) -> None:
        """Clear faults on the devices (fault reset, reboot) and leave torque off."""

    def _on_fault(self) -> None:
        """Bring devices to their safe state after a fault (default: torque off, best effort)."""
        self._disable()
