"""Realtime scheduling within a CPU budget, for the threads on an input's way to the bus besides the loop's own.

A packet's way to the bus crosses the input's receive thread in the API server process and the bus process's
wake-up; at normal scheduling on a busy two-core host each waits milliseconds for a CPU behind the emulators and
other work. Under SCHED_FIFO (below the control loop's priority) they run as soon as their packet or their targets
arrive. A sender that floods a port, or a driver that spins, must not turn that into a core taken from everything
else, so each keeps a budget: once its thread has used more than ``share`` of a ``window`` of CPU time it drops to
normal scheduling for the rest of the window (its work still goes on, at normal priority), and takes realtime
scheduling back in the next window (:meth:`RealtimeBudget.spent` after each piece of work, :meth:`RealtimeBudget.rearm`
before waiting again). Without permission (no CAP_SYS_NICE) the thread keeps normal scheduling.

A budget can also hold a whole process (``whole_process``: every thread's scheduling changes together, and the CPU
time of all of them counts). A bus process needs that: its driver's receive thread (python-can's notifier) takes the
interpreter lock for every frame, and at normal scheduling it is preempted while holding it, behind the emulators,
so the realtime write thread waits for the lock for milliseconds (a priority inversion through the lock). So does the
API server: its show-control input threads wait for the lock behind its request and telemetry threads. The threads
of such a process share one budget object (its methods take a lock), and any of them may call :meth:`enter` (again:
the threads started since are raised too).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time

log = logging.getLogger(__name__)

#: Share of one CPU an input thread may take at realtime priority, and the window it is measured over (s).
SHARE = 0.2
WINDOW_S = 0.1


class RealtimeBudget:
    """SCHED_FIFO at ``priority`` for the thread that calls :meth:`enter` (or, ``whole_process``, for all of its
    process's threads; 0: leave it), within a budget of CPU time spent at that priority (``share`` of each
    ``window_s``)."""

    def __init__(self, priority: int, share: float = SHARE, window_s: float = WINDOW_S,
                 whole_process: bool = False) -> None:
        self.priority = int(priority)
        self.whole_process = whole_process
        self._clock = time.process_time if whole_process else time.thread_time
        self.budget = share * window_s
        self.window_s = window_s
        self.realtime = False  # the calling thread is under SCHED_FIFO now
        self.demoted = 0  # windows in which the budget ran out
        self._window_end = 0.0
        self._used = 0.0  # CPU time spent realtime in this window, up to the last change
        self._since = 0.0  # CPU time (the thread's, or the process's) when it last became realtime
        # the threads of a process share a whole-process budget; a thread's own needs no lock
        self._lock: threading.Lock | contextlib.nullcontext[None] = (
            threading.Lock() if whole_process else contextlib.nullcontext())

    def enter(self) -> str:
        """Raise the calling thread, or with ``whole_process`` every thread of the process (call it first thing on
        that thread; for a process, again after starting more threads); returns what happened."""
        if self.priority <= 0:
            return "normal scheduling"
        with self._lock:
            if self.whole_process and self._window_end > 0.0:  # entered before: raise the threads started since
                if self.realtime:
                    self._set(True, restart=False)
                return f"SCHED_FIFO {self.priority}"
            self._window_end = time.monotonic() + self.window_s
            self._used = 0.0
            if not self._set(True):
                self._window_end = 0.0
                return "normal scheduling (SCHED_FIFO not permitted)"
            return f"SCHED_FIFO {self.priority}"

    def used(self) -> float:
        """CPU time (s) spent realtime in the current window."""
        return self._used + (self._clock() - self._since if self.realtime else 0.0)

    def spent(self) -> None:
        """After each packet: drop to normal scheduling while over budget, take realtime back in a new window."""
        if self._window_end == 0.0:
            return
        with self._lock:
            if time.monotonic() >= self._window_end:
                self._rearm()
                return
            if self.realtime and self.used() > self.budget:
                self.demoted += 1
                self._lower()

    def keep_for_urgent(self, share: float) -> None:
        """Before work that is not urgent: normal scheduling for it once more than ``share`` of this window's budget
        is used, so the rest stays for the urgent work (:meth:`rearm` takes realtime back, within the budget)."""
        with self._lock:
            if self.realtime and self.used() > share * self.budget:
                self._lower()

    def lower(self) -> None:
        """Normal scheduling until :meth:`rearm` (e.g. the rest of a transaction need not preempt anything)."""
        with self._lock:
            self._lower()

    def rearm(self) -> None:
        """Back to realtime scheduling unless this window's budget is spent (call it before waiting again)."""
        if self._window_end == 0.0:
            return
        with self._lock:
            self._rearm()

    def _lower(self) -> None:
        if self.realtime:
            self._used += self._clock() - self._since
            self._set(False)

    def _rearm(self) -> None:
        now = time.monotonic()
        if now >= self._window_end:
            if self.realtime:
                self._since = self._clock()
            self._window_end = now + self.window_s
            self._used = 0.0
        if not self.realtime and self._used <= self.budget:
            self._set(True)

    def _set(self, realtime: bool, restart: bool = True) -> bool:
        policy, param = (os.SCHED_FIFO, self.priority) if realtime else (os.SCHED_OTHER, 0)
        try:
            for tid in self._threads():
                try:
                    os.sched_setscheduler(tid, policy, os.sched_param(param))
                except ProcessLookupError:  # a thread that ended meanwhile
                    continue
        except (AttributeError, OSError) as exc:
            log.debug("thread scheduling unchanged: %s", exc)
            return False
        self.realtime = realtime
        if realtime and restart:
            self._since = self._clock()
        return True

    def _threads(self) -> list[int]:
        """The threads to schedule: the calling one (0), or every thread of the process."""
        if not self.whole_process:
            return [0]
        try:
            return [int(tid) for tid in os.listdir("/proc/self/task")]
        except OSError:
            return [0]


def as_budget(priority: int | RealtimeBudget) -> RealtimeBudget:
    """A thread's budget at SCHED_FIFO ``priority`` (0: normal scheduling), or the shared budget given (a whole
    process's, whose threads all call it)."""
    return priority if isinstance(priority, RealtimeBudget) else RealtimeBudget(priority)
