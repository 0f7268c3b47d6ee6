"""CANopen CiA 402 bus cycle: the ``canopen402`` driver against emulated drives, vs. the physical CAN budget.

:func:`measure` runs full cycles (write RPDOs + SYNC, wait until every drive's TPDOs for that SYNC
arrived, read) in two set-ups measured in the same run: everything in one process on a python-can
``virtual`` bus, and the drives in a ``likeness sim canopen`` subprocess reached over the
socketcand bridge on loopback. The physical reference is the wire time of the same frames on a
1 Mbit/s CAN bus, computed from CAN 2.0A frame sizes below; ``ratio_to_can`` > 1 means software is
slower than the wire. Run directly: ``python -m benchmarks._bus_canopen [n_motors] [cycles]``.
"""

from __future__ import annotations

import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BITRATE = 1_000_000
MAX_LOAD = 0.7  # usual design limit for bus load
#: Generous supervision timeouts: a benchmark on a shared machine measures latency, not fault handling.
BENCH_OPTIONS = {"heartbeat_timeout_s": 0.5, "feedback_timeout_s": 0.5, "stale_cycles": 50}

#: Frames of one cycle of this driver, per drive: RPDO1 (controlword + target, 6 bytes),
#: TPDO1 (statusword + position, 6 bytes), TPDO2 (velocity + current + error code, 8 bytes); plus one SYNC.
DRIVER_FRAMES_PER_DRIVE = (6, 6, 8)
#: The minimal CiA 402 cyclic position exchange (FACTS.md): one RPDO and one TPDO of 8 bytes per drive.
MINIMAL_FRAMES_PER_DRIVE = (8, 8)


def can_frame_bits(data_bytes: int, *, worst_case_stuffing: bool = False) -> int:
    """Bits on the wire for one CAN 2.0A (11-bit id) data frame, including the 3-bit intermission.

    SOF 1 + id 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15 + CRC delimiter 1 + ACK 2 +
    EOF 7 + IFS 3 = 47 + 8n. Stuffing can add one bit per 4 bits of the 34 + 8n bits from SOF to the
    CRC in the worst case: ⌊(34 + 8n − 1) / 4⌋.
    """
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 bytes, got {data_bytes}")
    bits = 47 + 8 * data_bytes
    if worst_case_stuffing:
        bits += (34 + 8 * data_bytes - 1) // 4
    return bits


def can_budget(n_motors: int, per_drive: tuple[int, ...] = DRIVER_FRAMES_PER_DRIVE) -> dict[str, float]:
    """Wire time of one cycle (SYNC + ``per_drive`` frames per drive) at 1 Mbit/s, and the rates it allows."""
    frames = [0] + list(per_drive) * n_motors  # the SYNC has no data
    nominal = sum(can_frame_bits(n) for n in frames) / BITRATE
    worst = sum(can_frame_bits(n, worst_case_stuffing=True) for n in frames) / BITRATE
    return {
        "frames_per_cycle": len(frames),
        "cycle_s_nominal": nominal,
        "cycle_s_worst_stuffing": worst,
        "max_rate_hz_at_70pct_load": MAX_LOAD / worst,
        "max_rate_hz_at_100pct_nominal": 1.0 / nominal,
    }


def _motors(n_motors: int) -> list[Any]:
    from drivers.base import MotorConfig

    return [
        MotorConfig.rotary(f"m{i}", i, counts_per_rev=4096, gear_ratio=10.0, min_position=-1.0, max_position=1.0,
                           max_velocity=5.0)
        for i in range(1, n_motors + 1)
    ]


def _cycles(bus: Any, cycles: int, warmup: int = 20) -> dict[str, float]:
    """Time ``cycles`` full write → feedback → read cycles after ``warmup`` untimed ones."""
    bus.open()
    bus.enable()
    try:
        start = {name: s.position for name, s in bus.read().items()}
        times: list[float] = []
        timeouts = 0
        t_start = time.perf_counter()
        for i in range(warmup + cycles):
            t = time.perf_counter() - t_start
            offset = 0.05 * math.sin(2.0 * math.pi * t)
            t0 = time.perf_counter()
            bus.write({name: pos + offset for name, pos in start.items()})
            if not bus.wait_for_feedback(0.25):
                timeouts += 1
            bus.read()
            if i >= warmup:
                times.append(time.perf_counter() - t0)
    finally:
        bus.close()
    times.sort()
    p99 = times[min(len(times) - 1, math.ceil(0.99 * len(times)) - 1)]
    return {"median_s": statistics.median(times), "p99_s": p99, "max_s": times[-1], "timeouts": timeouts}


def _measure_virtual(n_motors: int, cycles: int) -> dict[str, float]:
    from drivers.canopen402 import CanOpen402Bus
    from sim_hardware.canopen.network import DriveSet

    channel = f"bench-canopen-{uuid.uuid4().hex[:8]}"
    with DriveSet(range(1, n_motors + 1), channel=channel):
        bus = CanOpen402Bus("bench", {"interface": "virtual", "channel": channel, **BENCH_OPTIONS}, _motors(n_motors))
        return _cycles(bus, cycles)


def _measure_socketcand(n_motors: int, cycles: int) -> dict[str, float]:
    from drivers.canopen402 import CanOpen402Bus

    proc = subprocess.Popen(
        [sys.executable, "-m", "likeness", "sim", "canopen", "--nodes", f"1-{n_motors}", "--port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        match = re.search(r"on socketcand ([\d.]+):(\d+) channel (\S+)", line)
        if not match:
            raise RuntimeError(f"emulator did not start: {line!r}")
        options = {"interface": "socketcand", "host": match.group(1), "port": int(match.group(2)),
                   "channel": match.group(3), **BENCH_OPTIONS}
        bus = CanOpen402Bus("bench", options, _motors(n_motors))
        return _cycles(bus, cycles)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def measure(n_motors: int, cycles: int) -> dict[str, Any]:
    """Median/p99 full-cycle time in-process and across processes, and the ratio to the CAN wire time."""
    if not 1 <= n_motors <= 127:
        raise ValueError(f"n_motors must be 1..127 (CANopen node ids), got {n_motors}")
    if cycles < 1:
        raise ValueError(f"cycles must be positive, got {cycles}")
    budget = can_budget(n_motors)
    wire = budget["cycle_s_worst_stuffing"]
    result: dict[str, Any] = {
        "n_motors": n_motors,
        "cycles": cycles,
        "can_1mbit": budget,
        "can_1mbit_minimal_layout": can_budget(n_motors, MINIMAL_FRAMES_PER_DRIVE),
    }
    for name, run in (("virtual", _measure_virtual), ("socketcand", _measure_socketcand)):
        stats = run(n_motors, cycles)
        stats["ratio_to_can"] = stats["median_s"] / wire
        stats["p99_ratio_to_can"] = stats["p99_s"] / wire
        result[name] = stats
    return result


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 13
    c = int(sys.argv[2]) if len(sys.argv) > 2 else 500
    print(json.dumps(measure(n, c), indent=2))
