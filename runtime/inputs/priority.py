"""Realtime scheduling for a show-control input's receive thread, with a CPU budget that a flood cannot exceed.

A packet's way to the bus crosses the input's thread in the API server process; at normal scheduling on a busy
two-core host that thread waits milliseconds for a CPU behind the emulators and other work. Under SCHED_FIFO (below
the control loop's priority) it runs as soon as its packet arrives. A sender that floods the port must not turn
that into a core taken from the bus processes, so each thread keeps a budget: once it has used more than ``share``
of a ``window`` of CPU time it drops to normal scheduling for the rest of the window (its packets still go through,
at normal priority), and takes realtime scheduling back in the next window. Without permission (no CAP_SYS_NICE)
the thread keeps normal scheduling.
"""

from __future__ import annotations

import logging
import os
import time

log = logging.getLogger(__name__)

#: Share of one CPU an input thread may take at realtime priority, and the window it is measured over (s).
SHARE = 0.2
WINDOW_S = 0.1


class InputPriority:
    """SCHED_FIFO at ``priority`` for the thread that calls :meth:`enter` (0: leave it), within a CPU budget."""

    def __init__(self, priority: int, share: float = SHARE, window_s: float = WINDOW_S) -> None:
        self.priority = int(priority)
        self.budget = share * window_s
        self.window_s = window_s
        self.realtime = False  # the calling thread is under SCHED_FIFO now
        self.demoted = 0  # windows in which the budget ran out
        self._window_end = 0.0
        self._cpu_at_start = 0.0

    def enter(self) -> str:
        """Raise the calling thread (call it first thing on the input's thread); returns what happened."""
        if self.priority <= 0:
            return "normal scheduling"
        if not self._set(True):
            return "normal scheduling (SCHED_FIFO not permitted)"
        self._window_end = time.monotonic() + self.window_s
        self._cpu_at_start = time.thread_time()
        return f"SCHED_FIFO {self.priority}"

    def spent(self) -> None:
        """After each packet: drop to normal scheduling while over budget, take realtime back in a new window."""
        if self.priority <= 0:
            return
        now = time.monotonic()
        if now >= self._window_end:
            self._window_end = now + self.window_s
            self._cpu_at_start = time.thread_time()
            if not self.realtime:
                self._set(True)
            return
        if self.realtime and time.thread_time() - self._cpu_at_start > self.budget:
            self.demoted += 1
            self._set(False)

    def _set(self, realtime: bool) -> bool:
        try:
            if realtime:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            else:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError) as exc:
            log.debug("input thread scheduling unchanged: %s", exc)
            return False
        self.realtime = realtime
        return True
