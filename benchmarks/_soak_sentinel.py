"""Bare realtime loops beside the soak's daemon, one pinned to each CPU: the machine's own stalls.

Each wakes at the daemon's rate and priority (SCHED_FIFO where permitted), does no work and records every deadline it
missed. A deadline missed by a loop that does nothing means its CPU ran no top-priority thread for a whole period:
time the hypervisor took from that virtual CPU (it takes one while the other runs), or the kernel's own work there.
The soak sets the daemon's misses beside these, so a report tells what the machine caused from what the daemon did.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from typing import Any


def _run(rate_hz: float, priority: int, cpu: int | None, conn: Any) -> None:
    """A sentinel process (on ``cpu`` only, when given): wait for deadlines until asked to stop; send (time,
    deadlines missed, lateness) of each miss."""
    import os

    from runtime.loop import RateScheduler, try_realtime

    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})
    _ok, message = try_realtime(priority)
    conn.send(message)
    sched = RateScheduler(1.0 / rate_hz, 0.0)  # sleeps to each deadline: its own load stays about 2 % of a core
    misses: list[tuple[float, int, float]] = []
    while not conn.poll(0):
        late, missed = sched.wait()
        if missed:
            misses.append((time.monotonic(), missed, late))
    conn.recv()
    conn.send(misses)


class Sentinel:
    """One bare loop per CPU (``cpu`` given: that one alone). Start with :meth:`start`; :meth:`stop` returns the
    misses of all of them in time order ((monotonic time, deadlines missed, lateness s))."""

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
                misses += [tuple(m) for m in (conn.recv() if conn.poll(10.0) else [])]
            except (OSError, EOFError):
                pass
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
        return sorted(misses)
