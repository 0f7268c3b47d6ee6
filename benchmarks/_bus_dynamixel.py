"""Dynamixel bus cycle timing: ``DynamixelBus`` against the emulator, in-process and across processes.

``measure(n_motors, cycles)`` runs full write + read cycles (one sync write of goal positions,
one sync read of the driver's 12-byte state block) and reports median and p99 against the wire
time of the same cycle on a physical RS-485 bus, computed from protocol 2.0 packet sizes.
"""

from __future__ import annotations

import math
import os
import re
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BITS_PER_BYTE = 10  # 8N1 framing
STATE_BYTES = 12  # hardware error, torque, current (2), velocity (4), position (4) via indirect data
GOAL_BYTES = 4


def cycle_bytes(n: int, *, fast: bool, data: int = STATE_BYTES) -> int:
    """Bytes on the wire for one sync write of goals plus one sync read of ``data`` bytes from ``n`` servos."""
    sync_write = 14 + n * (1 + GOAL_BYTES)  # header 4, id, length 2, instruction, address 2, size 2, CRC 2
    sync_read = 14 + n  # same fields, then one id per servo
    # fast sync read: one packet (header..instruction, then error, id, data, CRC per servo);
    # sync read: a status packet per servo (header 4, id, length 2, 0x55, error, data, CRC 2)
    status = 8 + n * (data + 4) if fast else n * (11 + data)
    return sync_write + sync_read + status


def bus_budget_s(n: int, baudrate: int, return_delay_us: float = 0.0, *, fast: bool = True,
                 data: int = STATE_BYTES) -> float:
    """Wire time of one cycle (USB adapter latency not included); return delay once per answering packet."""
    delays = (1 if fast else n) * return_delay_us * 1e-6
    return cycle_bytes(n, fast=fast, data=data) * BITS_PER_BYTE / baudrate + delays


def _motors(n: int) -> list[Any]:
    from drivers.base import MotorConfig

    return [MotorConfig.rotary(f"m{i}", i, counts_per_rev=4096, min_position=-0.5, max_position=0.5,
                               max_velocity=6.0, zero_count=2048) for i in range(1, n + 1)]


def _run_cycles(port: str, n: int, cycles: int) -> tuple[list[float], int, float]:
    """Cycle times, cycles whose read timed out (tolerated up to 10 in a row), CPU seconds of this process."""
    from drivers.dynamixel import DynamixelBus

    options = {"port": port, "baudrate": 4_000_000, "return_delay_us": 0, "max_consecutive_failures": 10}
    bus = DynamixelBus("bench", options, _motors(n))
    times: list[float] = []
    timeouts = 0
    with bus:
        bus.enable()
        names = list(bus.motors)
        t0 = time.monotonic()
        cpu0 = time.process_time()
        for _ in range(cycles):
            target = 0.2 * math.sin(2 * math.pi * 0.5 * (time.monotonic() - t0))
            start = time.perf_counter()
            bus.write(dict.fromkeys(names, target))
            stamp = bus.read()[names[0]].timestamp
            times.append(time.perf_counter() - start)
            timeouts += stamp < start_mono(start)
        cpu = time.process_time() - cpu0
        bus.disable()
    return times, timeouts, cpu


def start_mono(perf_start: float) -> float:
    """The monotonic time matching a perf_counter reading (a stale state predates the cycle)."""
    return time.monotonic() - (time.perf_counter() - perf_start)


def _summary(run: tuple[list[float], int, float]) -> dict[str, float]:
    times, timeouts, cpu = run
    ordered = sorted(times)
    return {
        "timeouts": timeouts,
        # CPU time of the measuring process per cycle (in-process: driver and emulator threads together);
        # unlike wall time it does not grow when other processes load the machine
        "cpu_per_cycle_s": cpu / len(times),
        "median_s": statistics.median(ordered),
        "p99_s": ordered[min(len(ordered) - 1, math.ceil(0.99 * len(ordered)) - 1)],
    }


def _in_process(n: int, cycles: int) -> dict[str, float]:
    from sim_hardware.dynamixel import DynamixelEmulator

    with DynamixelEmulator(range(1, n + 1), initial_positions=2048) as emu:
        return _summary(_run_cycles(emu.port, n, cycles))


def _across_processes(n: int, cycles: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        link = os.path.join(tmp, "dxl")
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        proc = subprocess.Popen(
            [sys.executable, "-m", "likeness", "sim", "dynamixel", "--ids", f"1-{n}", "--link", link,
             "--initial-position", "2048"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        try:
            assert proc.stdout is not None
            ready, _, _ = select.select([proc.stdout], [], [], 30.0)
            line = proc.stdout.readline() if ready else ""
            if not re.match(r"^ready: ", line):
                raise RuntimeError(f"emulator did not start: {line!r}")
            return _summary(_run_cycles(link, n, cycles))
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def measure(n_motors: int, cycles: int) -> dict:
    """Time ``cycles`` full cycles for ``n_motors`` servos, in-process and across processes.

    The top level describes the in-process run (how the runtime uses a simulated bus):
    ``transport``, ``median_s``, ``p99_s``, ``budget_s`` (wire time of the same cycle at the
    4 Mbaud the driver runs at) and ``ratio`` (median / budget). ``rows`` holds both transports
    in that form; ``budgets_s`` the wire time at 1 and 4 Mbaud and at 1 Mbaud with the factory
    500 µs return delay.
    """
    if not 1 <= n_motors <= 252:
        raise ValueError(f"n_motors must be in 1..252, got {n_motors}")
    if cycles < 1:
        raise ValueError(f"cycles must be positive, got {cycles}")
    budgets = {
        "1M": bus_budget_s(n_motors, 1_000_000),
        "4M": bus_budget_s(n_motors, 4_000_000),
        "1M_return_delay_500us": bus_budget_s(n_motors, 1_000_000, 500.0, fast=False),
    }
    rows = []
    for transport, run in (("in-process", _in_process), ("across processes", _across_processes)):
        stats = run(n_motors, cycles)
        rows.append({
            "backend": "dynamixel",
            "transport": transport,
            "n_motors": n_motors,
            "cycles": cycles,
            **stats,
            "budget_s": budgets["4M"],
            "ratio": stats["median_s"] / budgets["4M"],
            "ratio_1M": stats["median_s"] / budgets["1M"],
        })
    return {**rows[0], "rows": rows, "budgets_s": budgets, "bus_rate_hz": {k: 1.0 / v for k, v in budgets.items()}}


def main() -> int:
    """Print the measurement for 13 and 40 servos."""
    for n in (13, 40):
        result = measure(n, 300)
        for r in result["rows"]:
            print(f"{n:>3} servos {r['transport']:<17} median {r['median_s'] * 1e3:7.3f} ms  "
                  f"p99 {r['p99_s'] * 1e3:7.3f} ms  wire @4M {r['budget_s'] * 1e3:6.3f} ms "
                  f"(ratio {r['ratio']:5.2f})  @1M ratio {r['ratio_1M']:5.2f}  "
                  f"cpu/cycle {r['cpu_per_cycle_s'] * 1e3:6.3f} ms  timeouts {r['timeouts']}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
