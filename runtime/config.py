"""The daemon's settings: the ``[runtime]``, ``[safety]`` and ``[api]`` tables of a head spec, validated.

Every table and key is optional (defaults below). Errors are :class:`~models.errors.SpecError`s naming the file,
the key and the bad value. ``overrides`` (``{"runtime.rate_hz": 500, ...}``) let tools and tests change single
values without editing the file.
"""

from __future__ import annotations

import ipaddress
import math
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from models.errors import SpecError
from models.headspec import HeadSpec

MAX_RATE_HZ = 1000.0


@dataclass(frozen=True)
class RuntimeSettings:
    """``[runtime]``: loop rate and scheduling, telemetry rate, streaming and recording."""

    rate_hz: float = 250.0
    telemetry_hz: float = 50.0
    realtime: bool = True  # try SCHED_FIFO for the control thread
    priority: int = 80  # SCHED_FIFO priority when permitted
    # SCHED_FIFO priority of the bus processes (0: normal scheduling at raised niceness, the default). Measured on the
    # sample head (benchmarks/daemon_loop.py --set runtime.bus_priority=10): realtime bus processes cost the loop
    # deadlines on 2 cores (260 missed of 9,565 at 1 kHz against 16), so leave it 0 unless the host has cores to spare.
    # (Emulated devices keep normal scheduling too: the CANopen emulator takes ~60 % of a core, too much to run above
    # the API server.)
    bus_priority: int = 0
    # SCHED_FIFO priority of the API server process, all its threads (requests, telemetry, the show-control inputs),
    # within one CPU budget (runtime.rtbudget: runtime.server.SERVER_SHARE, 30 % of a core per 100 ms, then normal
    # scheduling for the rest of the window), so a flood of requests cannot take a core from the bus processes. One
    # budget for the whole process: an input thread realtime alone waited for the interpreter lock behind the request
    # or telemetry thread, preempted on a busy host while holding it (benchmarks/input_latency.py at 500 Hz: send ->
    # received p99 1.1-2.0 ms with the input threads alone realtime, 0.9-1.3 ms with the whole process). 0: normal
    # scheduling at raised niceness, the inputs' receive threads at inputs_priority.
    api_priority: int = 20
    # With api_priority = 0: SCHED_FIFO priority of the show-control inputs' receive threads (OSC, sACN, timecode;
    # 0: normal scheduling), each within a CPU budget of its own (runtime.rtbudget: 20 % of a core over 100 ms).
    inputs_priority: int = 20
    # SCHED_FIFO priority of each bus process, all its threads, within a CPU budget (runtime.rtbudget: 60 % of a core
    # per 100 ms, then normal scheduling for the rest of the window), so a driver that spins cannot take a core; new
    # targets then reach the bus at once instead of after the emulators and other work of a busy host (0: normal
    # scheduling). Ignored when bus_priority > 0 (the whole process realtime without a budget) or realtime = false.
    bus_write_priority: int = 30
    cpu: int = -1  # pin the control thread to this CPU (-1: no pinning)
    spin_us: float = 200.0  # sleep until this long before a deadline, then spin
    switch_interval_s: float = 0.0005  # sys.setswitchinterval while the loop runs (other threads yield sooner)
    stream_delay_s: float = 0.05  # jitter buffer: streamed frames play this long after their timestamp
    stream_phase_lock: bool = False  # slide the loop's phase to just after a steady stream's frames (runtime.phaselock)
    # without wake on input: wanted time from a locked frame reaching the daemon (the API server's receipt stamp) to
    # the cycle that plays it; it covers the hop from the server to the loop (a frame that reaches the loop later
    # waits a whole period). With wake on input the lock centres frames in their slots instead (runtime.runner)
    stream_phase_lead_s: float = 0.0006
    # run the cycle as soon as a live value (OSC, sACN), a timecode sample or a stream frame due before the next
    # deadline reaches the loop, instead of at that deadline: at most one cycle per period slot and none closer than
    # a quarter period to the one before, the shaper advancing by the time that really passed (runtime.runner)
    wake_on_input: bool = True
    stream_max_ahead_s: float = 30.0  # frames further in the future are refused
    stream_max_frames: int = 20000  # jitter buffer capacity
    record_dir: str = "recordings"  # where ``record`` writes (relative to the working directory)
    record_max_s: float = 600.0
    auto_enable: bool = False  # enable torque right after start-up
    clip_memory_bytes: int = 256 << 20  # memory budget of all loaded clips (compiled arrays)


@dataclass(frozen=True)
class SafetySettings:
    """``[safety]``: watchdog, safe speed, fault and e-stop reactions."""

    watchdog_hold_s: float = 0.25  # no stream data this long: hold the last command
    watchdog_neutral_s: float = 1.0  # ... and after this long: ease to neutral at safe speed
    safe_speed: float = 0.25  # fraction of each actuator's max velocity for pose/neutral moves
    fault_action: str = "disable"  # after a fault: "disable" torque on every bus, or "hold" (stop commanding)
    estop_action: str = "disable"
    feedback_timeout_s: float = 0.25  # default of each [buses.NAME] feedback_fault_s (feedback this old faults)


@dataclass(frozen=True)
class ApiSettings:
    """``[api]``: endpoints, message limits and optional CURVE authentication."""

    command: str = "tcp://127.0.0.1:5555"
    telemetry: str = "tcp://127.0.0.1:5556"
    allow_remote: bool = False  # binding anything but loopback needs this (and CURVE, or insecure_remote)
    insecure_remote: bool = False  # allow_remote without CURVE: plain text on the network, on purpose
    max_message_bytes: int = 1 << 20  # larger requests get a too_large error reply
    hard_max_message_bytes: int = 16 << 20  # larger ones are dropped by ZeroMQ (peer disconnected)
    curve_secret_key: str = ""  # server secret key file (from ``likeness keys``); empty: no CURVE
    curve_allow_dir: str = ""  # directory of allowed client public keys


@dataclass(frozen=True)
class DaemonConfig:
    """All daemon settings of one head."""

    runtime: RuntimeSettings = field(default_factory=RuntimeSettings)
    safety: SafetySettings = field(default_factory=SafetySettings)
    api: ApiSettings = field(default_factory=ApiSettings)


_TABLES: dict[str, type] = {"runtime": RuntimeSettings, "safety": SafetySettings, "api": ApiSettings}


def daemon_config(head: HeadSpec, overrides: Mapping[str, Any] | None = None) -> DaemonConfig:
    """Validate the daemon tables of ``head``; ``overrides`` maps ``"table.key"`` to a value."""
    source = str(head.source)
    merged: dict[str, dict[str, Any]] = {t: dict(head.section(t)) for t in _TABLES}
    for dotted, value in (overrides or {}).items():
        table, _, key = dotted.partition(".")
        if table not in _TABLES or not key:
            raise SpecError("<overrides>", dotted, "must be runtime.KEY, safety.KEY or api.KEY")
        merged[table][key] = value
    built = {}
    for table, cls in _TABLES.items():
        built[table] = _build(cls, merged[table], table, source)
    cfg = DaemonConfig(**built)
    _check(cfg, source, head)
    return cfg


def _build(cls: type, raw: Mapping[str, Any], table: str, source: str) -> Any:
    defaults = cls()
    known = {f.name: f for f in fields(cls)}
    values: dict[str, Any] = {}
    for key, value in raw.items():
        if key not in known:
            raise SpecError(source, f"{table}.{key}", f"unknown key; allowed: {', '.join(sorted(known))}", value)
        default = getattr(defaults, key)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise SpecError(source, f"{table}.{key}", "must be true or false", value)
        elif isinstance(default, int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise SpecError(source, f"{table}.{key}", "must be an integer", value)
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise SpecError(source, f"{table}.{key}", "must be a finite number", value)
            value = float(value)
        elif isinstance(default, str) and not isinstance(value, str):
            raise SpecError(source, f"{table}.{key}", "must be a string", value)
        values[key] = value
    return replace(defaults, **values)


def _check(cfg: DaemonConfig, source: str, head: HeadSpec) -> None:
    from drivers.registry import available_backends

    rt, sf, api = cfg.runtime, cfg.safety, cfg.api

    def need(ok: bool, key: str, message: str, value: Any) -> None:
        if not ok:
            raise SpecError(source, key, message, value)

    known = available_backends()
    for bus in head.buses.values():
        need(bus.driver in known, f"buses.{bus.name}.driver", f"unknown driver; known: {', '.join(known)}",
             bus.driver)

    need(1.0 <= rt.rate_hz <= MAX_RATE_HZ, "runtime.rate_hz", f"must lie in [1, {MAX_RATE_HZ:g}]", rt.rate_hz)
    need(0 < rt.telemetry_hz <= rt.rate_hz, "runtime.telemetry_hz", "must lie in (0, rate_hz]", rt.telemetry_hz)
    need(1 <= rt.priority <= 99, "runtime.priority", "must lie in [1, 99]", rt.priority)
    need(0 <= rt.bus_priority < rt.priority, "runtime.bus_priority", "must lie in [0, priority)", rt.bus_priority)
    need(0 <= rt.api_priority < rt.priority, "runtime.api_priority", "must lie in [0, priority)", rt.api_priority)
    need(0 <= rt.bus_write_priority < rt.priority, "runtime.bus_write_priority", "must lie in [0, priority)",
         rt.bus_write_priority)
    need(0 <= rt.inputs_priority < rt.priority, "runtime.inputs_priority", "must lie in [0, priority)",
         rt.inputs_priority)
    need(0 <= rt.spin_us <= 1e6 / rt.rate_hz, "runtime.spin_us", "must lie in [0, one period]", rt.spin_us)
    need(1e-5 <= rt.switch_interval_s <= 0.1, "runtime.switch_interval_s", "must lie in [1e-5, 0.1]",
         rt.switch_interval_s)
    need(rt.stream_phase_lead_s > 0 and (not rt.stream_phase_lock or rt.stream_phase_lead_s <= 0.5 / rt.rate_hz),
         "runtime.stream_phase_lead_s", "must be positive and, with stream_phase_lock, at most half a loop period",
         rt.stream_phase_lead_s)
    need(0 <= rt.stream_delay_s <= 5, "runtime.stream_delay_s", "must lie in [0, 5] s", rt.stream_delay_s)
    need(0 < rt.stream_max_ahead_s <= 3600, "runtime.stream_max_ahead_s", "must lie in (0, 3600] s",
         rt.stream_max_ahead_s)
    need(2 <= rt.stream_max_frames <= 1_000_000, "runtime.stream_max_frames", "must lie in [2, 1e6]",
         rt.stream_max_frames)
    need(bool(rt.record_dir), "runtime.record_dir", "must not be empty", rt.record_dir)
    need(1 << 16 <= rt.clip_memory_bytes <= 1 << 34, "runtime.clip_memory_bytes", "must lie in [64 KiB, 16 GiB]",
         rt.clip_memory_bytes)
    need(0 < rt.record_max_s <= 86400, "runtime.record_max_s", "must lie in (0, 86400] s", rt.record_max_s)
    need(sf.watchdog_hold_s > 0, "safety.watchdog_hold_s", "must be positive", sf.watchdog_hold_s)
    need(sf.watchdog_hold_s <= sf.watchdog_neutral_s, "safety.watchdog_neutral_s",
         "must be at least watchdog_hold_s", sf.watchdog_neutral_s)
    need(0 < sf.safe_speed <= 1, "safety.safe_speed", "must lie in (0, 1] (fraction of max velocity)", sf.safe_speed)
    need(sf.fault_action in ("disable", "hold"), "safety.fault_action", "must be 'disable' or 'hold'",
         sf.fault_action)
    need(sf.estop_action in ("disable", "hold"), "safety.estop_action", "must be 'disable' or 'hold'",
         sf.estop_action)
    need(sf.feedback_timeout_s > 2.0 / rt.rate_hz, "safety.feedback_timeout_s", "must exceed two loop periods",
         sf.feedback_timeout_s)
    for key in ("command", "telemetry"):
        endpoint = getattr(api, key)
        problem = endpoint_problem(endpoint, api.allow_remote)
        need(problem is None, f"api.{key}", problem or "", endpoint)
    need(1024 <= api.max_message_bytes <= api.hard_max_message_bytes, "api.max_message_bytes",
         "must lie in [1024, hard_max_message_bytes]", api.max_message_bytes)
    need(bool(api.curve_secret_key) == bool(api.curve_allow_dir), "api.curve_allow_dir",
         "CURVE needs both curve_secret_key and curve_allow_dir", api.curve_allow_dir)
    need(not api.allow_remote or bool(api.curve_secret_key) or api.insecure_remote, "api.allow_remote",
         "remote clients without CURVE authentication would command the head in plain text: configure "
         "curve_secret_key and curve_allow_dir (likeness keys), or set insecure_remote = true on purpose",
         api.allow_remote)
    if api.curve_secret_key:
        base = head.source.parent
        for key in ("curve_secret_key", "curve_allow_dir"):
            p = resolve(base, getattr(api, key))
            need(p.exists(), f"api.{key}", "does not exist", str(p))


def resolve(base: Path, path: str) -> Path:
    """``path`` relative to ``base`` unless absolute."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base / p)


def endpoint_problem(endpoint: str, allow_remote: bool) -> str | None:
    """Why ``endpoint`` may not be bound (None when fine): tcp or ipc only; tcp on loopback unless allowed."""
    if endpoint.startswith(("ipc://", "inproc://")):
        return None
    if not endpoint.startswith("tcp://"):
        return "must be a tcp://, ipc:// or inproc:// endpoint"
    parsed = urllib.parse.urlsplit(endpoint[:-2] + ":0" if endpoint.endswith(":*") else endpoint)
    host = parsed.hostname or ""
    try:
        port = parsed.port
    except ValueError:
        return "has a bad port"
    if port is None:
        return "needs a port (or * for any free port)"
    if host == "localhost":
        return None
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not allow_remote:
        return "binds beyond loopback; set api.allow_remote = true (and use CURVE) to allow it"
    return None
