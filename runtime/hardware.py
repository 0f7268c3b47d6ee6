"""All motor buses of one head behind a single object, built from its :class:`~models.headspec.HeadSpec`.

:class:`Hardware` turns actuator specs into :class:`~drivers.base.MotorConfig`s, starts in-process emulators for
buses marked ``simulated = true`` (through :mod:`runtime.simhw`, imported only then), and creates the drivers through
:mod:`drivers.registry`. Reads and writes are keyed by actuator name and split per bus; values are SI.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

from drivers.base import LifecycleState, MotorBus, MotorConfig, MotorState
from drivers.errors import BusInitError, BusTimeout, CommandRejected
from drivers.registry import create_bus
from models.headspec import ActuatorSpec, HeadSpec

log = logging.getLogger(__name__)


def motor_config(act: ActuatorSpec) -> MotorConfig:
    """The driver-side config of one actuator: device id, encoder scaling and hard limits in SI.

    Rotary: ``counts_per_rev`` at the motor and ``gear_ratio`` motor turns per output turn. Linear: the same, with
    the actuator option ``lead_mm`` (output travel per motor turn, default 1 mm).
    """
    opts = dict(act.options)
    if act.kind == "rotary":
        return MotorConfig.rotary(
            act.name, act.device_id, counts_per_rev=act.counts_per_rev, min_position=act.min,
            max_position=act.max, max_velocity=act.max_velocity, gear_ratio=act.gear_ratio,
            direction=act.direction, zero_count=act.zero_count, options=opts,
        )
    lead_m = float(opts.get("lead_mm", 1.0)) * 1e-3
    return MotorConfig(
        name=act.name, device_id=act.device_id,
        counts_per_unit=act.direction * act.counts_per_rev * act.gear_ratio / lead_m,
        min_position=act.min, max_position=act.max, max_velocity=act.max_velocity,
        zero_count=act.zero_count, kind="linear", options=opts,
    )


class Hardware:
    """All buses of a head: builds MotorConfigs from the HeadSpec, starts in-process emulators for buses with
    ``simulated = true``, creates drivers through ``drivers.registry``."""

    #: Opening an emulated bus is retried this often on a timeout (real buses: once).
    SIMULATED_OPEN_ATTEMPTS = 3

    def __init__(
        self,
        head: HeadSpec,
        buses: Mapping[str, MotorBus],
        simulators: Mapping[str, Any] | None = None,
    ) -> None:
        self.head = head
        self.buses: Mapping[str, MotorBus] = dict(buses)
        self._sims: dict[str, Any] = dict(simulators or {})
        self._bus_of: dict[str, str] = {}
        for bus_name, bus in self.buses.items():
            for motor in bus.motors:
                self._bus_of[motor] = bus_name
        self.configs: dict[str, MotorConfig] = {
            name: bus.motors[name] for bus in self.buses.values() for name in bus.motors
        }

    @classmethod
    def from_head(cls, head: HeadSpec) -> Hardware:
        """Create (not open) every bus of ``head``; simulated buses get a freshly started in-process emulator."""
        buses: dict[str, MotorBus] = {}
        sims: dict[str, Any] = {}
        try:
            for bus_name, spec in head.buses.items():
                acts = head.actuators_on(bus_name)
                if not acts:
                    log.warning("bus %s has no actuators; skipped", bus_name)
                    continue
                motors = [motor_config(a) for a in acts]
                options = dict(spec.options)
                if spec.simulated:
                    from runtime import simhw

                    sim = simhw.start(spec.driver, bus_name, options, motors, {a.name: a.neutral for a in acts})
                    sims[bus_name] = sim
                    options = sim.options
                buses[bus_name] = create_bus(spec.driver, bus_name, options, motors)
        except BaseException:
            for sim in sims.values():
                sim.close()
            raise
        return cls(head, buses, sims)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open every bus (torque stays off); on failure the buses already opened are closed again."""
        opened: list[MotorBus] = []
        try:
            for name, bus in self.buses.items():
                attempts = self.SIMULATED_OPEN_ATTEMPTS if name in self._sims else 1
                for attempt in range(1, attempts + 1):
                    try:
                        bus.open()
                        break
                    except (BusTimeout, BusInitError) as exc:
                        # An emulator shares this host's CPU; under load it can miss a driver's fixed reply window
                        # (and a late reply can then be misread as the answer to the next request).
                        if attempt == attempts:
                            raise
                        log.warning("bus %s: open attempt %d failed (%s); retrying", name, attempt, exc)
                        _quiet(bus.close)
                opened.append(bus)
        except BaseException:
            for bus in opened:
                _quiet(bus.close)
            raise

    def enable(self) -> None:
        """Torque on, holding present positions; any failure disables every bus again."""
        try:
            for bus in self.buses.values():
                if bus.state is not LifecycleState.ACTIVE:
                    bus.enable()
        except BaseException:
            self.disable()
            raise

    def disable(self) -> None:
        """Torque off on every bus that is active (best effort: one failing bus does not stop the others)."""
        errors: list[BaseException] = []
        for bus in self.buses.values():
            if bus.state is LifecycleState.ACTIVE:
                try:
                    bus.disable()
                except Exception as exc:
                    log.exception("bus %s: disable failed", bus.name)
                    errors.append(exc)
        if errors:
            raise errors[0]

    def reset_fault(self) -> None:
        """Clear faults on every faulted bus (they return to inactive, torque off)."""
        for bus in self.buses.values():
            if bus.state is LifecycleState.FAULT:
                bus.reset_fault()

    def close(self) -> None:
        """Close every bus and stop the emulators; never raises."""
        for bus in self.buses.values():
            _quiet(bus.close)
        for sim in self._sims.values():
            _quiet(sim.close)
        self._sims.clear()

    def __enter__(self) -> Hardware:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ state
    @property
    def states(self) -> dict[str, LifecycleState]:
        """Lifecycle state of each bus."""
        return {name: bus.state for name, bus in self.buses.items()}

    def faults(self) -> dict[str, tuple[int, str]]:
        """Active faults of every bus, keyed ``"bus/device"``."""
        out: dict[str, tuple[int, str]] = {}
        for name, bus in self.buses.items():
            for dev, fault in bus.faults().items():
                out[f"{name}/{dev}"] = fault
        return out

    def bus_of(self, actuator: str) -> str:
        """Name of the bus that carries ``actuator``."""
        return self._bus_of[actuator]

    # ------------------------------------------------------------------ cyclic I/O
    def read(self) -> dict[str, MotorState]:
        """Latest state of every motor, by actuator name."""
        out: dict[str, MotorState] = {}
        for bus in self.buses.values():
            out.update(bus.read())
        return out

    def write(self, targets: Mapping[str, float]) -> None:
        """Command SI position targets by actuator name (split per bus); unknown names are refused first."""
        per_bus: dict[str, dict[str, float]] = {}
        for name, value in targets.items():
            bus = self._bus_of.get(name)
            if bus is None:
                raise CommandRejected(f"unknown actuator {name!r}")
            per_bus.setdefault(bus, {})[name] = value
        for bus_name, values in per_bus.items():
            self.buses[bus_name].write(values)

    # ------------------------------------------------------------------ emulation
    def simulated_positions(self) -> dict[str, float]:
        """Ground-truth SI positions of emulated motors, read on the emulator side (not through the drivers)."""
        out: dict[str, float] = {}
        for bus_name, sim in self._sims.items():
            counts = sim.positions_counts()
            for name, cfg in self.buses[bus_name].motors.items():
                c = counts.get(cfg.device_id)
                if c is not None and math.isfinite(c):
                    out[name] = cfg.from_counts(c)
        return out

    def emulator(self, bus: str) -> Any:
        """The emulator object of a simulated bus, for fault injection; KeyError if ``bus`` is not simulated."""
        try:
            return self._sims[bus].emulator
        except KeyError:
            raise KeyError(f"bus {bus!r} is not simulated (simulated: {', '.join(sorted(self._sims)) or 'none'})")\
                from None


def _quiet(fn: Any) -> None:
    try:
        fn()
    except Exception:
        log.exception("ignored error during shutdown")
