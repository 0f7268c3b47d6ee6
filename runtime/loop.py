"""Fixed-rate scheduling for the control thread: realtime priority when permitted, and loop statistics.

The scheduler sleeps until ``spin`` before each deadline and then spins, which keeps wake-up jitter in the
microseconds under SCHED_FIFO. Statistics cover wake-up lateness (jitter), cycle work time and missed deadlines
(a cycle starting more than one period late); the most recent samples are kept in a fixed ring buffer.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sys
import time
from collections.abc import Callable

import numpy as np

log = logging.getLogger(__name__)


def try_realtime(priority: int) -> tuple[bool, str]:
    """Put the calling thread under SCHED_FIFO at ``priority``; returns (ok, message saying what happened)."""
    if not hasattr(os, "sched_setscheduler"):
        return False, "SCHED_FIFO not available on this platform; running with normal priority"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return False, "SCHED_FIFO not permitted (needs root or CAP_SYS_NICE / rtprio limit); normal priority"
    except OSError as exc:
        return False, f"SCHED_FIFO failed ({exc}); running with normal priority"
    return True, f"control thread runs SCHED_FIFO priority {priority}"


def process_threads() -> dict[int, str]:
    """This process's threads, native id → name (from ``/proc/self/task``; empty where there is no such list)."""
    out: dict[int, str] = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                out[int(tid)] = f.read().strip()
        except OSError:  # the thread ended meanwhile
            continue
    return out


def drop_realtime() -> None:
    """Back to normal scheduling for the calling thread (best effort)."""
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def freeze_heap() -> None:
    """Collect once and move every object allocated so far out of the collector's reach (``gc.freeze``)."""
    gc.collect()
    gc.freeze()


class LoopStats:
    """Ring buffers of wake-up lateness and work time per cycle, plus counters."""

    def __init__(self, period: float, window: int = 4096) -> None:
        self.period = period
        self.window = window
        self.lateness = np.zeros(window)
        self.work = np.zeros(window)
        self.periods = np.zeros(window)
        self._last_start: float | None = None
        self.n = 0
        self.missed = 0
        self.skipped = 0  # cycles not run because a lifecycle transition held the loop
        self.early = 0  # cycles run on an input's arrival ahead of their deadline (not in the rings: no deadline)

    def add(self, lateness: float, work: float, start: float | None = None) -> None:
        """One cycle: wake-up lateness, work time and (optionally) its start time, for the measured period."""
        i = self.n % self.window
        self.lateness[i] = lateness
        self.work[i] = work
        if start is not None:
            self.periods[i] = start - self._last_start if self._last_start is not None else self.period
            self._last_start = start
        self.n += 1

    def reset(self) -> None:
        """Forget the cycles counted so far (the ring buffers are overwritten from the start)."""
        self.n = self.missed = self.skipped = self.early = 0
        self._last_start = None

    def summary(self) -> dict[str, float | int]:
        """p50/p99/max of jitter and work time in microseconds, counts of cycles and misses."""
        k = min(self.n, self.window)
        out: dict[str, float | int] = {"rate_hz": 1.0 / self.period, "cycles": self.n, "missed": self.missed,
                                       "skipped": self.skipped, "early": self.early}
        if k:
            lat = np.abs(self.lateness[:k]) * 1e6
            wk = self.work[:k] * 1e6
            p = np.percentile(lat, [50, 99])
            w = np.percentile(wk, [50, 99])
            per = self.periods[:k] * 1e6
            out.update(period_mean_us=float(per.mean()), period_max_us=float(per.max()),
                       jitter_p50_us=float(p[0]), jitter_p99_us=float(p[1]), jitter_max_us=float(lat.max()),
                       work_p50_us=float(w[0]), work_p99_us=float(w[1]), work_max_us=float(wk.max()))
        return out


class RateScheduler:
    """Deadlines every ``period`` seconds on the monotonic clock; :meth:`wait` sleeps, then spins, to the next one."""

    def __init__(self, period: float, spin: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = period
        self.spin = spin
        self.clock = clock
        self.next = clock() + period
        self.early = False  # the last wait ended ahead of its deadline, on the idle function's word

    def wait(self, idle: Callable[[float], bool | None] | None = None) -> tuple[float, int]:
        """Block until the next deadline; returns (lateness in s, deadlines missed since the previous call).

        ``idle(until)``, when given, is called instead of sleeping and must return by the absolute time ``until``
        (the runner takes commands that arrive in the meantime). When it returns True the wait ends at once, ahead
        of the deadline (:attr:`early`; the lateness is then negative): that deadline counts as served, and the
        next one is a period after it, so at most one cycle runs per period slot."""
        clock = self.clock
        target = self.next
        now = clock()
        remaining = target - now - self.spin
        self.early = False
        if remaining > 0:
            if idle is None:
                time.sleep(remaining)
            elif idle(target - self.spin):
                self.early = True
                self.next = target + self.period
                return clock() - target, 0
        while clock() < target:
            pass
        now = clock()
        late = now - target
        missed = 0
        if late > self.period:
            missed = int(late // self.period)
            target += missed * self.period  # skip ahead instead of bursting to catch up
        self.next = target + self.period
        return late, missed


class SwitchInterval:
    """Context manager that lowers ``sys.setswitchinterval`` so other threads hand the GIL back sooner."""

    def __init__(self, interval: float) -> None:
        self.interval = interval
        self._old = sys.getswitchinterval()

    def __enter__(self) -> SwitchInterval:
        self._old = sys.getswitchinterval()
        sys.setswitchinterval(self.interval)
        return self

    def __exit__(self, *exc: object) -> None:
        sys.setswitchinterval(self._old)
