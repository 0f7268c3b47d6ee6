"""All motor buses of one head behind a single object, built from its :class:`~models.headspec.HeadSpec`.

Both facades turn actuator specs into :class:`~drivers.base.MotorConfig`s and start an emulator child process for
each bus marked ``simulated = true`` (through :mod:`runtime.simhw`, imported only then):

- :class:`LinkedHardware` runs every bus in a process of its own (:class:`runtime.buslink.BusLink`): the control
  loop posts targets and takes feedback without ever waiting on a bus.
- :class:`Hardware` calls the drivers synchronously in the caller's thread: for calibration, which moves one pose at
  a time and waits on encoder readings, and as the baseline of ``benchmarks/bus_isolation.py``.

Values are SI; reads and writes are keyed by actuator name (or per bus in link order).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from drivers.base import LifecycleState, MotorBus, MotorConfig, MotorState
from drivers.errors import BusError, BusInitError, BusTimeout, CommandRejected
from drivers.registry import create_bus
from models.headspec import ActuatorSpec, HeadSpec
from runtime.buslink import BusFeedback, BusLink

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


def start_emulators(
    head: HeadSpec, *, nice: int | None = None
) -> tuple[dict[str, list[MotorConfig]], dict[str, dict[str, Any]], dict[str, Any]]:
    """Motor configs and driver options per bus of ``head``, with an emulator process started (at its actuators'
    neutral positions) for each simulated bus; returns (motors, options, emulators) keyed by bus name.
    Buses without actuators are skipped with a warning. On failure the emulators already started are stopped."""
    motors: dict[str, list[MotorConfig]] = {}
    options: dict[str, dict[str, Any]] = {}
    sims: dict[str, Any] = {}
    try:
        for bus_name, spec in head.buses.items():
            acts = head.actuators_on(bus_name)
            if not acts:
                log.warning("bus %s has no actuators; skipped", bus_name)
                continue
            motors[bus_name] = [motor_config(a) for a in acts]
            options[bus_name] = spec.driver_options()
            if spec.simulated:
                from runtime import simhw

                sim = simhw.start(spec.driver, bus_name, options[bus_name], motors[bus_name],
                                  {a.name: a.neutral for a in acts},
                                  nice=simhw.EMULATOR_NICE if nice is None else nice)
                sims[bus_name] = sim
                options[bus_name] = sim.options
    except BaseException:
        for sim in sims.values():
            sim.close()
        raise
    return motors, options, sims


def _simulated_positions(sims: Mapping[str, Any], configs: Mapping[str, Mapping[str, MotorConfig]]) -> dict[str, float]:
    out: dict[str, float] = {}
    for bus_name, sim in sims.items():
        counts = sim.positions_counts()
        for name, cfg in configs[bus_name].items():
            c = counts.get(cfg.device_id)
            if c is not None and math.isfinite(c):
                out[name] = cfg.from_counts(c)
    return out


def _emulator(sims: Mapping[str, Any], bus: str) -> Any:
    try:
        return sims[bus]
    except KeyError:
        raise KeyError(f"bus {bus!r} is not simulated (simulated: {', '.join(sorted(sims)) or 'none'})") from None


class Hardware:
    """All buses of a head with their drivers called synchronously in the caller's thread (calibration, benchmarks);
    simulated buses reach their emulator child processes."""

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
        """Create (not open) every bus of ``head``; simulated buses get a freshly started emulator process."""
        buses: dict[str, MotorBus] = {}
        motors, options, sims = start_emulators(head)
        try:
            for bus_name in motors:
                buses[bus_name] = create_bus(head.buses[bus_name].driver, bus_name, options[bus_name],
                                             motors[bus_name])
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
        return _simulated_positions(self._sims, {n: b.motors for n, b in self.buses.items()})

    def emulator(self, bus: str) -> Any:
        """The emulator (:class:`runtime.simhw.SimProcess`) of a simulated bus, for fault injection and ground
        truth; KeyError if ``bus`` is not simulated."""
        return _emulator(self._sims, bus)


def _quiet(fn: Any) -> None:
    try:
        fn()
    except Exception:
        log.exception("ignored error during shutdown")


class LinkedHardware:
    """All buses of a head, each in its own process behind a :class:`~runtime.buslink.BusLink`.

    Build with :meth:`from_head` (emulators start there), then :meth:`start` (spawn and open every bus, torque off).
    The loop side uses :meth:`post` and :meth:`feedback` per bus (non-blocking, link order: ``links[bus].actuators``);
    lifecycle goes through :meth:`request`/:meth:`results`, or :meth:`call` where blocking is fine.
    """

    #: Opening an emulated bus is retried this often (real buses: once).
    SIMULATED_OPEN_ATTEMPTS = 3

    def __init__(
        self, head: HeadSpec, links: Mapping[str, BusLink], simulators: Mapping[str, Any] | None = None
    ) -> None:
        self.head = head
        self.links: dict[str, BusLink] = dict(links)
        self._sims: dict[str, Any] = dict(simulators or {})
        self._bus_of = {name: bus for bus, link in self.links.items() for name in link.actuators}
        self.configs: dict[str, MotorConfig] = {
            name: cfg for link in self.links.values() for name, cfg in link.motors.items()
        }

    @classmethod
    def from_head(
        cls,
        head: HeadSpec,
        *,
        idle_hz: float = 100.0,
        realtime_priority: int | None = None,
        emulator_nice: int | None = None,
        bus_nice: int = 0,
    ) -> LinkedHardware:
        """Start the emulators of simulated buses and create (not start) a link per bus.

        ``idle_hz`` is the feedback rate of a bus that gets no targets; ``realtime_priority`` asks for SCHED_FIFO in
        the bus processes; ``emulator_nice`` is added to the emulator processes' niceness (default
        :data:`runtime.simhw.EMULATOR_NICE`); ``bus_nice`` is added to the bus processes' niceness.
        """
        motors, options, sims = start_emulators(head, nice=emulator_nice)
        links = {
            bus: BusLink(head.buses[bus].driver, bus, options[bus], motors[bus], idle_hz=idle_hz,
                         realtime_priority=realtime_priority, nice=bus_nice,
                         open_attempts=cls.SIMULATED_OPEN_ATTEMPTS if bus in sims else 1)
            for bus in motors
        }
        return cls(head, links, sims)

    def start(self, timeout_s: float = 60.0) -> None:
        """Spawn every bus process and open its bus (torque off); on failure every link is stopped again."""
        try:
            for link in self.links.values():
                link.start(timeout_s)
        except BaseException:
            for link in self.links.values():
                link.stop()
            raise

    def stop(self) -> None:
        """Stop every bus process (torque off, close) and every emulator; idempotent, never raises."""
        for link in self.links.values():
            _quiet(link.stop)
        for sim in self._sims.values():
            _quiet(sim.close)
        self._sims.clear()

    def __enter__(self) -> LinkedHardware:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ loop side
    def post(self, bus: str, targets: np.ndarray) -> None:
        """Latest SI targets of one bus, in ``links[bus].actuators`` order; never blocks."""
        self.links[bus].post(targets)

    def feedback(self) -> dict[str, BusFeedback]:
        """Latest feedback of every bus; never blocks."""
        return {bus: link.feedback() for bus, link in self.links.items()}

    def request(self, op: str) -> dict[str, int]:
        """Ask every bus for ``op`` (``enable``, ``disable``, ``reset``); tickets by bus."""
        return {bus: link.request(op) for bus, link in self.links.items()}

    def results(self, tickets: Mapping[str, int]) -> dict[str, tuple[bool, str]] | None:
        """Outcome per bus once every request of ``tickets`` is done; None while any is pending."""
        out: dict[str, tuple[bool, str]] = {}
        for bus, ticket in tickets.items():
            res = self.links[bus].result(ticket)
            if res is None:
                return None
            out[bus] = res
        return out

    def call(self, op: str, timeout_s: float = 10.0) -> None:
        """Carry out ``op`` on every bus and wait; raises BusError naming the buses that failed."""
        tickets = self.request(op)
        deadline = time.monotonic() + timeout_s
        pending = dict(tickets)
        failed: list[str] = []
        while pending:
            for bus, ticket in list(pending.items()):
                res = self.links[bus].result(ticket)
                if res is not None:
                    del pending[bus]
                    if not res[0]:
                        failed.append(f"{bus}: {res[1]}")
            if pending and time.monotonic() > deadline:
                failed.extend(f"{bus}: {op} did not complete in {timeout_s:g} s" for bus in pending)
                break
            time.sleep(0.002)
        if failed:
            raise BusError(f"{op} failed on " + "; ".join(failed))

    # ------------------------------------------------------------------ state
    def bus_of(self, actuator: str) -> str:
        """Name of the bus that carries ``actuator``."""
        return self._bus_of[actuator]

    def positions(self) -> dict[str, float]:
        """Latest measured SI positions by actuator name (NaN before a bus's first read)."""
        out: dict[str, float] = {}
        for link in self.links.values():
            out.update(zip(link.actuators, link.feedback().positions.tolist(), strict=True))
        return out

    def faults(self) -> dict[str, tuple[int, str]]:
        """Active faults of every bus, keyed ``"bus/device"``."""
        return {f"{bus}/{dev}": f for bus, link in self.links.items() for dev, f in link.feedback().faults.items()}

    def simulated_positions(self) -> dict[str, float]:
        """Ground-truth SI positions of emulated motors, from the emulator processes (not through the drivers)."""
        return _simulated_positions(self._sims, {bus: link.motors for bus, link in self.links.items()})

    def emulator(self, bus: str) -> Any:
        """The :class:`runtime.simhw.SimProcess` of a simulated bus; KeyError if ``bus`` is not simulated."""
        return _emulator(self._sims, bus)
