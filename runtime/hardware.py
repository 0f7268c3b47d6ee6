"""All motor buses of one head behind a single object, built from its :class:`~models.headspec.HeadSpec`.

:class:`Hardware` runs every bus in a process of its own behind a :class:`runtime.bus.BusProxy`: the control loop
posts targets and takes feedback without ever waiting on a bus. It turns actuator specs into
:class:`~drivers.base.MotorConfig`s and starts an emulator child process for each bus marked ``simulated = true``
(:mod:`runtime.simhw`). Values are SI; targets and feedback go per bus in the proxy's actuator order.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping

import numpy as np

from drivers.base import MotorConfig
from drivers.errors import BusError
from models.headspec import ActuatorSpec, HeadSpec
from runtime import simhw
from runtime.bus import BusFeedback, BusProxy
from runtime.bus.config import DriverOptions

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
    head: HeadSpec, *, nice: int | None = None, initial: Mapping[str, float] | None = None
) -> tuple[dict[str, list[MotorConfig]], dict[str, DriverOptions], dict[str, simhw.SimProcess]]:
    """Motor configs and driver options per bus of ``head``, with an emulator process started (at its actuators'
    neutral positions, or ``initial[name]`` in SI where given) for each simulated bus; returns (motors, options,
    emulators) keyed by bus name.
    Buses without actuators are skipped with a warning. On failure the emulators already started are stopped."""
    motors: dict[str, list[MotorConfig]] = {}
    options: dict[str, DriverOptions] = {}
    sims: dict[str, simhw.SimProcess] = {}
    try:
        for bus_name, spec in head.buses.items():
            acts = head.actuators_on(bus_name)
            if not acts:
                log.warning("bus %s has no actuators; skipped", bus_name)
                continue
            motors[bus_name] = [motor_config(a) for a in acts]
            options[bus_name] = spec.driver_options()
            if spec.simulated:
                sim = simhw.start(spec.driver, bus_name, options[bus_name], motors[bus_name],
                                  {a.name: (initial or {}).get(a.name, a.neutral) for a in acts},
                                  nice=simhw.EMULATOR_NICE if nice is None else nice)
                sims[bus_name] = sim
                options[bus_name] = sim.options
    except BaseException:
        for sim in sims.values():
            sim.close()
        raise
    return motors, options, sims


def _quiet(fn: Callable[[], object]) -> None:
    try:
        fn()
    except Exception:
        log.exception("ignored error during shutdown")


class Hardware:
    """All buses of a head, each in its own process behind a :class:`~runtime.bus.BusProxy`.

    Build with :meth:`from_head` (emulators start there), then :meth:`start` (spawn and open every bus, torque off).
    The loop side uses each bus's proxy (``proxies``: non-blocking ``post``/``feedback``, lifecycle through
    ``request``/``result``); :meth:`call` carries out a lifecycle operation on every bus where blocking is fine.
    """

    #: Opening an emulated bus is retried this often (real buses: once).
    SIMULATED_OPEN_ATTEMPTS = 3

    def __init__(
        self, head: HeadSpec, proxies: Mapping[str, BusProxy], simulators: Mapping[str, simhw.SimProcess] | None = None
    ) -> None:
        self.head = head
        self.proxies: dict[str, BusProxy] = dict(proxies)
        self._sims: dict[str, simhw.SimProcess] = dict(simulators or {})
        self._bus_of = {name: bus for bus, proxy in self.proxies.items() for name in proxy.actuators}

    @classmethod
    def from_head(
        cls,
        head: HeadSpec,
        *,
        idle_hz: float = 100.0,
        realtime_priority: int | None = None,
        emulator_nice: int | None = None,
        bus_nice: int = 0,
        write_priority: int = 0,
        initial: Mapping[str, float] | None = None,
    ) -> Hardware:
        """Start the emulators of simulated buses and create (not start) a bus proxy per bus.

        ``idle_hz`` is the feedback rate of a bus that gets no targets; ``realtime_priority`` asks for SCHED_FIFO in
        the bus processes; ``emulator_nice`` is added to the emulator processes' niceness (default
        :data:`runtime.simhw.EMULATOR_NICE`); ``bus_nice`` is added to the bus processes' niceness;
        ``write_priority`` runs them at SCHED_FIFO within a CPU budget (:class:`runtime.bus.config.BusProcessConfig`);
        ``initial`` places emulated actuators (SI, by name) elsewhere than at neutral, e.g. outside their limits.
        """
        motors, options, sims = start_emulators(head, nice=emulator_nice, initial=initial)
        proxies = {
            bus: BusProxy(head.buses[bus].driver, bus, options[bus], motors[bus], idle_hz=idle_hz,
                          realtime_priority=realtime_priority, nice=bus_nice, write_priority=write_priority,
                          open_attempts=cls.SIMULATED_OPEN_ATTEMPTS if bus in sims else 1)
            for bus in motors
        }
        return cls(head, proxies, sims)

    def start(self, timeout_s: float = 60.0) -> None:
        """Spawn every bus process and open its bus (torque off); on failure every bus process is stopped again."""
        try:
            for proxy in self.proxies.values():
                proxy.start(timeout_s)
        except BaseException:
            for proxy in self.proxies.values():
                proxy.stop()
            raise

    def stop(self) -> None:
        """Stop every bus process (torque off, close) and every emulator; idempotent, never raises."""
        for proxy in self.proxies.values():
            _quiet(proxy.stop)
        for sim in self._sims.values():
            _quiet(sim.close)
        self._sims.clear()

    # ------------------------------------------------------------------ loop side
    def post(self, bus: str, targets: np.ndarray) -> None:
        """Latest SI targets of one bus, in ``proxies[bus].actuators`` order; never blocks."""
        self.proxies[bus].post(targets)

    def feedback(self) -> dict[str, BusFeedback]:
        """Latest feedback of every bus; never blocks."""
        return {bus: proxy.feedback() for bus, proxy in self.proxies.items()}

    def call(self, op: str, timeout_s: float = 10.0) -> None:
        """Carry out ``op`` (``enable``, ``disable``, ``reset``) on every bus and wait (for start-up and tests; the
        loop runner requests per bus without waiting); raises BusError naming the buses that failed."""
        pending = {bus: proxy.request(op) for bus, proxy in self.proxies.items()}
        deadline = time.monotonic() + timeout_s
        failed: list[str] = []
        while pending:
            for bus, ticket in list(pending.items()):
                res = self.proxies[bus].result(ticket)
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
        for proxy in self.proxies.values():
            out.update(zip(proxy.actuators, proxy.feedback().positions.tolist(), strict=True))
        return out

    def faults(self) -> dict[str, tuple[int, str]]:
        """Active faults of every bus, keyed ``"bus/device"``."""
        return {f"{bus}/{dev}": f for bus, proxy in self.proxies.items()
                for dev, f in proxy.feedback().faults.items()}

    def simulated_positions(self) -> dict[str, float]:
        """Ground-truth SI positions of emulated motors, from the emulator processes (not through the drivers)."""
        out: dict[str, float] = {}
        for bus, sim in self._sims.items():
            counts = sim.positions_counts()
            for name, cfg in self.proxies[bus].motors.items():
                c = counts.get(cfg.device_id)
                if c is not None and math.isfinite(c):
                    out[name] = cfg.from_counts(c)
        return out

    def emulator(self, bus: str) -> simhw.SimProcess:
        """The emulator of a simulated bus, for fault injection and ground truth; KeyError if ``bus`` is not
        simulated."""
        try:
            return self._sims[bus]
        except KeyError:
            sims = ", ".join(sorted(self._sims)) or "none"
            raise KeyError(f"bus {bus!r} is not simulated (simulated: {sims})") from None
