"""A bus link's writes, watched from a process of its own: the input-latency benchmark's eye on the bus.

The benchmark times a packet to the first bus write that carries its value, by the bus process's own write stamp
(published with its feedback in the link's shared block, :mod:`runtime.bus.layout`). Polling that block from the
daemon's own process puts a thread beside the control loop that takes the GIL every 100-200 µs, which the loop then
waits for (a daemon's process runs no such thread). This watcher maps the block read-only in another process
(SCHED_FIFO 1 where permitted, sleeping between polls), keeps every write it sees (stamp, one actuator's target) and
hands them over on request; the stamps it reports are the bus process's, so its own polling delay does not count.
"""

from __future__ import annotations

import contextlib
import mmap
import multiprocessing as mp
import os
import time
from typing import Any

import numpy as np

from runtime.bus import layout as L

#: Seconds between polls: a write stays visible until the next one, at least a quarter period later (0.5 ms at
#: 500 Hz, 0.25 ms at 1 kHz). The stamps are the bus process's, so the polling delay does not count; each poll is a
#: realtime wake-up taken from the machine under test (alone: 17 % of a core at 0.1 ms, 9 % at 0.2 ms).
POLL_S = 200e-6


def _watch(path: str, n: int, j: int, conn: Any) -> None:
    """The watcher process: poll the block at ``path`` for writes of actuator ``j`` of ``n``; answer requests."""
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    lay = L.Layout(n)
    with open(path, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, prot=mmap.PROT_READ)
    views = lay.views(memoryview(buf))
    c = views.counters
    stamps: list[float] = [0.0]
    values: list[float] = [float("nan")]
    w = L.N_HEADER + 2 * n + j
    conn.send("ready")
    while True:
        done = int(c[L.C_FB_DONE])
        snap = views.feedback[done & 1]
        stamp, value = float(snap[L.H_WSTAMP]), float(snap[w])
        if int(c[L.C_FB_BEGUN]) < done + 2 and np.isfinite(stamp) and stamp != stamps[-1]:
            stamps.append(stamp)
            values.append(value)
        if conn.poll(0):
            req = conn.recv()
            if req is None:
                return
            k = int(np.searchsorted(stamps, float(req), side="right"))
            conn.send((stamps[k - 1:], values[k - 1:]))  # the last write at or before the time, then the later ones
        time.sleep(POLL_S)


class BusWatch:
    """Watch the writes of ``actuator`` on bus link ``link`` (a :class:`runtime.bus.BusProxy`, started)."""

    def __init__(self, link: Any, actuator: str) -> None:
        name = link._shm.name.lstrip("/")
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_watch, args=(f"/dev/shm/{name}", len(link.actuators),
                                                      link.actuators.index(actuator), child), daemon=True)
        self._proc.start()
        if not self._conn.poll(60.0):
            raise RuntimeError("the bus watcher did not start")
        self._conn.recv()  # watching from now on

    def since(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(write stamps, targets) of the last write at or before ``t`` and every write after it, seen so far."""
        self._conn.send(t)
        stamps, values = self._conn.recv()
        return np.array(stamps), np.array(values)

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(None)
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.kill()

    def __enter__(self) -> BusWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
