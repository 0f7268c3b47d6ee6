"""Bare realtime loops beside the soak's daemon, one pinned to each CPU: the machine's own stalls.

Each wakes at the daemon's rate and priority (SCHED_FIFO where permitted), does no work and records every deadline it
missed. A deadline missed by a loop that does nothing means its CPU ran no top-priority thread for a whole period:
time the hypervisor took from that virtual CPU (it takes one while the other runs), or the kernel's own work there.
The soak sets the daemon's misses beside these, so a report tells what the machine caused from what the daemon did.

A loop asleep between deadlines does not see a CPU that runs, but slowly (a busy sibling thread, the hypervisor
taking short slices): each wake-up therefore also times a fixed piece of interpreter work (:func:`_probe`, about 20
µs, about 1 % of a CPU at 500 Hz) and records the wake-ups where it took more than :data:`SLOW_FACTOR` times its
median over the first :data:`CALIBRATION` wake-ups: the moments when the same work took several times longer on
this machine, whatever the daemon was doing.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from typing import Any

#: A probe taking more than this many times its calibrated median is a slow wake-up.
SLOW_FACTOR = 3.0
#: Wake-ups whose probe times give the median.
CALIBRATION = 250


def _probe(n: int = 200) -> int:
    """A fixed piece of interpreter work (integer arithmetic in a loop, as the daemon's bookkeeping does)."""
    acc = 0
    for i in range(n):
        acc = (acc * 31 + i) & 0xFFFF
    return acc


def _run(rate_hz: float, priority: int, cpu: int | None, conn: Any) -> None:
    """A sentinel process (on ``cpu`` only, when given): wait for deadlines until asked to stop, timing the probe at
    each wake-up; send (misses: (time, deadlines missed, lateness) each; slow: (time, probe duration) each; the
    probe's calibrated median)."""
    import os

    from runtime.loop import RateScheduler, try_realtime

    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})
    _ok, message = try_realtime(priority)
    conn.send(message)
    sched = RateScheduler(1.0 / rate_hz, 0.0)  # sleeps to each deadline: its own load stays about 2 % of a core
    misses: list[tuple[float, int, float]] = []
    slow: list[tuple[float, float]] = []
    calibration: list[float] = []
    median = float("inf")
    clock = time.perf_counter
    while not conn.poll(0):
        late, missed = sched.wait()
        now = time.monotonic()
        if missed:
            misses.append((now, missed, late))
        t0 = clock()
        _probe()
        dt = clock() - t0
        if len(calibration) < CALIBRATION:
            calibration.append(dt)
            if len(calibration) == CALIBRATION:
                median = sorted(calibration)[CALIBRATION // 2]
        elif dt > SLOW_FACTOR * median:
            slow.append((now, dt))
    conn.recv()
    conn.send({"misses": misses, "slow": slow, "probe_median": median if calibration[CALIBRATION - 1:] else None})


class Sentinel:
    """One bare loop per CPU (``cpu`` given: that one alone). Start with :meth:`start`; :meth:`stop` returns the
    misses of all of them in time order ((monotonic time, deadlines missed, lateness s)); :attr:`slow` then holds
    their slow wake-ups in time order ((monotonic time, probe duration s)) and :attr:`probe_median` each loop's
    calibrated probe time (s)."""

    def __init__(self, rate_hz: float, priority: int, cpu: int | None = None) -> None:
        import os

        ctx = mp.get_context("spawn")
        cpus = [cpu] if cpu is not None else sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else [None]
        self._procs = []
        for c in cpus:
            conn, child = ctx.Pipe()
            self._procs.append((conn, ctx.Process(target=_run, args=(rate_hz, priority, c, child), daemon=True)))
        self.scheduling = ""
        self.slow: list[tuple[float, float]] = []
        self.probe_median: list[float] = []

    def start(self) -> Sentinel:
        for _, proc in self._procs:
            proc.start()
        said = {conn.recv() if conn.poll(60.0) else "did not start" for conn, _ in self._procs}
        self.scheduling = f"{len(self._procs)} pinned, one per CPU: " + "; ".join(sorted(said))
        return self

    def stop(self) -> list[tuple[float, int, float]]:
        misses: list[tuple[float, int, float]] = []
        for conn, proc in self._procs:
            try:
                conn.send(None)
                got = conn.recv() if conn.poll(10.0) else {}
                misses += [tuple(m) for m in got.get("misses", [])]
                self.slow += [tuple(x) for x in got.get("slow", [])]
                if got.get("probe_median") is not None:
                    self.probe_median.append(got["probe_median"])
            except (OSError, EOFError):
                pass
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
        self.slow.sort()
        return sorted(misses)
