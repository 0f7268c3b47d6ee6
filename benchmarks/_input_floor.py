"""What this machine itself costs a packet on the daemon's way to the bus, measured beside the daemon in one run.

A show-control packet crosses three process wake-ups before a bus process writes it: the input's receive thread
(UDP), the control loop (the command pipe) and the bus process (its wake-up pipe). The floor is the same chain with
nothing else in it: a sender process (SCHED_FIFO, as the benchmark's senders) sends a UDP datagram carrying its send
time to a receiver process at the input threads' priority, which writes it to a pipe read by a process at the loop's
priority, which writes it to a pipe read by a process at the bus processes' priority; the last stamps its arrival.
A single packet waits, besides, for the next control cycle (up to one period).

Measured twice: on the machine as it is (the idle floor), and beside a running daemon (its loop, bus processes and
emulated drives at work: the loaded floor, the same wake-ups competing for the same two cores, with the relay one
step below the loop's priority so that it never delays a cycle). The loaded floor is what the host itself costs the
packet's way at that load, before any of the daemon's own work on it.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import socket
import struct
import time
from typing import Any

_STAMP = struct.Struct("<d")


def _set_priority(fifo: int, nice: int = 0) -> None:
    try:
        if fifo > 0:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
        elif nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (AttributeError, OSError):
        pass  # without permission the floor is measured at normal scheduling, as the daemon would run


def _receiver(sock: socket.socket, w: int, fifo: int) -> None:
    """Hop 1: UDP → pipe."""
    _set_priority(fifo)
    while True:
        data = sock.recv(64)
        os.write(w, data)
        if _STAMP.unpack(data)[0] < 0:
            return


def _relay(r: int, w: int, fifo: int) -> None:
    """Hop 2: pipe → pipe (the loop's wake-up)."""
    _set_priority(fifo)
    while True:
        data = os.read(r, _STAMP.size)
        os.write(w, data)
        if _STAMP.unpack(data)[0] < 0:
            return


def _last(r: int, out: Any, fifo: int) -> None:
    """Hop 3: the bus process's wake-up; stamps each arrival."""
    _set_priority(fifo, -10)
    lat = []
    while True:
        data = os.read(r, _STAMP.size)
        sent = _STAMP.unpack(data)[0]
        if sent < 0:
            out.put(lat)
            return
        lat.append(time.monotonic() - sent)


def _sender(port: int, n: int, fifo: int, seed: int) -> None:
    import random

    _set_priority(fifo)
    rng = random.Random(seed)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for _ in range(n):
        time.sleep(rng.uniform(0.002, 0.006))
        s.sendto(_STAMP.pack(time.monotonic()), ("127.0.0.1", port))
    s.sendto(_STAMP.pack(-1.0), ("127.0.0.1", port))


def floor(n: int = 300, input_fifo: int = 20, loop_fifo: int = 80, bus_fifo: int = 30,
          sender_fifo: int = 10) -> list[float]:
    """Latencies (s) of ``n`` datagrams through the three-hop chain (see the module docstring); the defaults are
    the daemon's (``[runtime] inputs_priority``, ``priority``, ``bus_write_priority``)."""
    ctx = mp.get_context("fork")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    r1, w1 = os.pipe()
    r2, w2 = os.pipe()
    out = ctx.Queue()
    procs = [ctx.Process(target=_receiver, args=(sock, w1, input_fifo), daemon=True),
             ctx.Process(target=_relay, args=(r1, w2, loop_fifo), daemon=True),
             ctx.Process(target=_last, args=(r2, out, bus_fifo), daemon=True)]
    for p in procs:
        p.start()
    sender = ctx.Process(target=_sender, args=(port, n, sender_fifo, 1), daemon=True)
    sender.start()
    try:
        lat = out.get(timeout=60.0)
    finally:
        for p in (*procs, sender):
            p.join(2.0)
            if p.is_alive():
                p.kill()
        for fd in (r1, w1, r2, w2):
            os.close(fd)
        sock.close()
    return lat


def _serve(conn: Any) -> None:
    """The floor runner's process: measure :func:`floor` with the arguments asked for, until told None."""
    while True:
        args = conn.recv()
        if args is None:
            return
        conn.send(floor(*args))


class FloorRunner:
    """Measures :func:`floor` from a small process of its own, started (spawned) before the daemon: the chain's
    processes are forked from it, not from the daemon's process. Forking the daemon's process to measure beside it
    made its control loop miss deadlines (10 in the 1.5 s of a loaded floor at 500 Hz): every page the loop wrote
    after a fork was copied on its first write."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child,))  # not daemonic: it starts processes itself
        self._proc.start()

    def floor(self, *args: int) -> list[float]:
        self._conn.send(args)
        if not self._conn.poll(120.0):
            raise RuntimeError("the floor runner did not answer")
        return self._conn.recv()

    def close(self) -> None:
        if not self._proc.is_alive():
            return
        with contextlib.suppress(OSError):
            self._conn.send(None)
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()

    def __enter__(self) -> FloorRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
