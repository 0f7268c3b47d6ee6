"""What the loop thread was doing when it missed a deadline: the evidence a missed cycle leaves, kept for its event.

A deadline is missed when the loop wakes more than a period late. The cycle before ran over, commands taken between
cycles held the thread, or the thread was ready but did not run: preempted on its CPU, waiting for the interpreter lock
while another thread of its process ran, or the whole CPU stalled (the host). Each cycle the loop takes a snapshot of
its own thread at its start and at the end of its work (wall clock, its CPU time, the process's CPU time, its context
switches and page faults: ``getrusage(RUSAGE_THREAD)``, about half a microsecond); a wake-up past a deadline compares
it with the snapshots of the cycle before and keeps a :class:`MissRecord` naming the likeliest cause. The records ride
on the loop's ``deadline_miss`` event (``causes``), so a soak can tell the daemon's own misses from the host's.
"""

from __future__ import annotations

import resource
import time
from dataclasses import asdict, dataclass

#: Records kept between two ``deadline_miss`` events (one per second at most); later ones only count.
MAX_PENDING = 16
#: Other threads of the loop's process that ran this long in a late interval held the interpreter lock meanwhile.
OTHERS_CPU_S = 200e-6

_THREAD = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)


@dataclass(frozen=True, slots=True)
class MissRecord:
    """One late wake-up: the cycle before (work), what ran between cycles, and the loop thread's scheduling record
    from the cycle before's start to this wake-up (seconds, counts)."""

    t: float  # the deadline this wake-up served (the cycle's time)
    late_s: float
    missed: int
    work_s: float  # the cycle before: wall time from its start to the end of its work
    work_cpu_s: float  # the loop thread's CPU time in that work
    between_s: float  # commands taken between cycles since (their steps, wall)
    interval_s: float  # the cycle before's start to this wake-up
    others_cpu_s: float  # CPU time of the process's other threads in the interval
    voluntary: int  # the loop thread's voluntary context switches in the interval (sleeps, waits for a lock)
    involuntary: int  # ... involuntary ones (preempted while runnable)
    minor_faults: int
    major_faults: int
    cause: str

    def as_dict(self) -> dict[str, float | int | str]:
        return {(k[:-2] + "_ms" if k.endswith("_s") else k): (round(v * 1e3, 3) if k.endswith("_s") else v)
                for k, v in asdict(self).items()}


def classify(period: float, work_s: float, work_cpu_s: float, between_s: float, others_cpu_s: float,
             involuntary: int, major_faults: int) -> str:
    """The likeliest cause of a late wake-up, from the evidence (checked in this order):

    - ``work_off_cpu``: the cycle before ran past a period and its thread was off its CPU for most of it (preempted,
      or waiting for the interpreter lock);
    - ``work_slow``: it ran past a period on its CPU (more work, or a slowed CPU);
    - ``between_cycles``: commands taken between cycles held the thread for over half a period;
    - ``page_faults``: the thread waited for pages from disk;
    - ``interpreter_lock``: other threads of the loop's process ran for a while in the interval (one of them held the
      lock when the loop woke);
    - ``preempted``: the thread was taken off its CPU while runnable;
    - ``not_scheduled``: none of these: the thread slept past its wake-up without being preempted (its CPU ran
      something else first, or the host stalled the CPU)."""
    if work_s > period:
        return "work_off_cpu" if work_cpu_s < 0.5 * work_s else "work_slow"
    if between_s > 0.5 * period:
        return "between_cycles"
    if major_faults:
        return "page_faults"
    if others_cpu_s > OTHERS_CPU_S:
        return "interpreter_lock"
    if involuntary:
        return "preempted"
    return "not_scheduled"


class CycleForensics:
    """Snapshots of the loop thread per cycle, and the :class:`MissRecord` of each late wake-up."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.pending: list[MissRecord] = []
        self.kept = 0  # records made since the start (pending ones included)
        self._start: tuple[float, float, float, int, int, int, int] | None = None  # taken on the loop's thread
        self._work_end = (0.0, 0.0)
        self._between = 0.0

    @staticmethod
    def _snap() -> tuple[float, float, float, int, int, int, int]:
        ru = resource.getrusage(_THREAD)
        return (time.monotonic(), time.thread_time(), time.process_time(), ru.ru_nvcsw, ru.ru_nivcsw, ru.ru_minflt,
                ru.ru_majflt)

    def between(self, seconds: float) -> None:
        """Commands were taken between cycles for ``seconds``."""
        self._between += seconds

    def work_done(self) -> None:
        """The cycle's work ended (call after its last stage)."""
        self._work_end = (time.monotonic(), time.thread_time())

    def woke(self, t: float, late: float, missed: int) -> None:
        """A cycle starts (its deadline ``t``, ``late`` after it; ``missed`` deadlines skipped before it): keep a
        record when it missed any, then take this cycle's snapshot."""
        now = self._snap()
        if missed and self._start is not None:
            s, (end_wall, end_cpu) = self._start, self._work_end
            thread_cpu = now[1] - s[1]
            work_s = end_wall - s[0]
            work_cpu = end_cpu - s[1]
            others = max(0.0, (now[2] - s[2]) - thread_cpu)
            invol, major = now[4] - s[4], now[6] - s[6]
            rec = MissRecord(t, late, missed, work_s, work_cpu, self._between, now[0] - s[0], others, now[3] - s[3],
                             invol, now[5] - s[5], major,
                             classify(self.period, work_s, work_cpu, self._between, others, invol, major))
            self.kept += 1
            if len(self.pending) < MAX_PENDING:
                self.pending.append(rec)
        self._start = now
        self._work_end = (now[0], now[1])
        self._between = 0.0

    def take(self) -> list[dict[str, float | int | str]]:
        """The records kept since the last call, as event fields (milliseconds for durations)."""
        out = [r.as_dict() for r in self.pending]
        self.pending.clear()
        return out
