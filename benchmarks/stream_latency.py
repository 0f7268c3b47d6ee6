"""Frame-to-bus latency: a streamed frame's arrival at the daemon (the API server's receive time) to the bus write
that carries it (the bus process's write time), p50/p99, at the head's loop rate; and sustained frames per second.

Two latencies: a producer streaming steadily at the loop rate (the goal's case: the loop's phase lock slides the
cycles to just after the frames, ``runtime.phaselock``), measured on the frames where the value steps, and single
frames sent at random phases of the cycle (which wait for the next cycle: up to one period). Baselines measured in
the same run: a bare ZeroMQ PUSH→PULL one-way hop of the same msgpack frame (latency), the same steady stream with
the phase lock off, and bare DEALER→ROUTER request/reply round trips per second (throughput). The jitter buffer's
delay is 1 ms here. Run with nothing else on the machine:
``python benchmarks/stream_latency.py [--trials 200] [--rate 250] [--seconds 3]``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zmq

try:
    from benchmarks import _daemon as D
except ImportError:  # run as a script
    import _daemon as D


def bare_push_pull(n: int, frame: dict) -> list[float]:
    """One-way PUSH→PULL latency of a packed frame, in seconds (same process, loopback TCP)."""
    ctx = zmq.Context.instance()
    pull = ctx.socket(zmq.PULL)
    port = pull.bind_to_random_port("tcp://127.0.0.1")
    push = ctx.socket(zmq.PUSH)
    push.connect(f"tcp://127.0.0.1:{port}")
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        push.send(msgpack.packb(frame))
        msgpack.unpackb(pull.recv())
        out.append(time.perf_counter() - t0)
    push.close(0)
    pull.close(0)
    return out


def bare_router_rate(seconds: float) -> float:
    """Request/reply round trips per second through a bare ROUTER echo thread."""
    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            if router.poll(50):
                frames = router.recv_multipart()
                msg = msgpack.unpackb(frames[-1])
                router.send_multipart([*frames[:-1], msgpack.packb({"id": msg["id"], "ok": True})])

    th = threading.Thread(target=echo)
    th.start()
    dealer = ctx.socket(zmq.DEALER)
    dealer.connect(f"tcp://127.0.0.1:{port}")
    n, end = 0, time.perf_counter() + seconds
    while time.perf_counter() < end:
        dealer.send(msgpack.packb({"op": "stream", "id": n, "channels": ["jaw"], "frames": [[0.0, 1.0]]}))
        dealer.recv()
        n += 1
    stop.set()
    th.join()
    dealer.close(0)
    router.close(0)
    return n / seconds


def stream_latency(daemon, trials: int) -> list[float]:
    """Arrival of a frame stamped "now" → the first bus write whose jaw target moved (seconds)."""
    from models.client import Client

    link = next(lk for lk in daemon.buses if "jaw" in lk.actuators)
    j = link.actuators.index("jaw")
    lat: list[float] = []
    with Client(daemon.command_endpoint) as c:
        offset, _ = c.clock_offset()
        rng = np.random.default_rng(1)
        for _ in range(trials):
            time.sleep(rng.uniform(0, daemon.period))  # a random phase in the cycle
            settle = time.monotonic() + 1.0
            while np.any(np.abs(daemon.state.shaper.v) > 1e-9) and time.monotonic() < settle:
                time.sleep(0.002)
            fb = link.feedback()
            before, stamp0 = float(fb.written[j]), fb.write_stamp
            value = 4.0 if abs(np.degrees(before)) < 2.0 else 0.0  # always a move away from where it is
            r = c.call("stream", channels=["jaw"], frames=[[time.monotonic() + offset, value]])
            if not r["accepted"]:
                continue
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                fb = link.feedback()
                if fb.write_stamp > stamp0 and abs(float(fb.written[j]) - before) > 1e-9:
                    lat.append(fb.write_stamp - r["t_recv"])
                    break
                time.sleep(0.0001)
    return lat


def _producer(endpoint: str, rate: float, steps: int, seed: int, out: Any) -> None:
    """A show-control producer in a process of its own: one frame per request at ``rate`` Hz on a fixed grid, sent
    without waiting for replies (a DEALER socket, as a streaming client would), the jaw stepping between 0° and 4°
    every 0.5–0.7 s; puts the arrival times (``t_recv``) of the step frames on ``out``. It runs as a sender on a
    machine of its own would (:func:`external_sender`)."""
    sender = D.external_sender()
    from models.client import Client

    with Client(endpoint) as c:
        offset, _ = c.clock_offset()
    rng = np.random.default_rng(seed)
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    step_ids: set[int] = set()
    recv: list[float] = []
    counts: dict[str, Any] = {"replies": 0, "late": 0, "sender": sender}
    period = 1.0 / rate
    value, k, next_step = 0.0, 0, int(rng.integers(125, 175))
    t_next = time.monotonic() + period

    def replies() -> None:
        while sock.poll(0):
            r = msgpack.unpackb(sock.recv())
            counts["replies"] += 1
            counts["late"] += int(r.get("late", 0) or 0)
            if r.get("id") in step_ids and r.get("ok") and r.get("accepted"):
                recv.append(r["t_recv"])

    give_up = time.monotonic() + 30.0 + 2.0 * steps  # a faulted or refusing daemon ends the measurement
    while len(recv) < steps and time.monotonic() < give_up:
        replies()
        D.sleep_until(t_next)
        t_next += period
        k += 1
        if k == next_step:
            value = 4.0 if value == 0.0 else 0.0
            next_step = k + int(rng.integers(125, 175))
            step_ids.add(k)
        sock.send(msgpack.packb({"op": "stream", "id": k, "channels": ["jaw"],
                                 "frames": [[time.monotonic() + offset, value]]}))
    sock.close(0)
    out.put((recv, counts))


def steady_latency(daemon, rate: float, steps: int, seed: int) -> tuple[list[float], dict[str, Any]]:
    """For each step frame of a steady producer (:func:`_producer`, its own process), its arrival → the first bus
    write that moved the jaw (seconds); this process watches the bus writes meanwhile."""
    stamps, values, (recv, counts) = D.run_sender_watching_jaw(
        daemon, _producer, (daemon.command_endpoint, rate, steps, seed), "producer")
    lat = D.first_moves(stamps, values, recv)
    return lat, counts


def throughput(daemon, seconds: float, batch: int) -> tuple[float, float]:
    """Frames per second accepted (and late) with ``batch`` frames per request, as fast as replies allow."""
    from models.client import Client

    names = list(daemon.names)
    accepted = late = 0
    with Client(daemon.command_endpoint) as c:
        offset, _ = c.clock_offset()
        start = time.monotonic()
        k = 0
        while (now := time.monotonic()) - start < seconds:
            base = now + offset + 0.001
            frames = [[base + 1e-5 * (k + j), *([1.0] * len(names))] for j in range(batch)]
            k += batch
            r = c.call("stream", channels=names, frames=frames)
            accepted += r["accepted"]
            late += r["late"]
        dt = time.monotonic() - start
    return accepted / dt, late / dt


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--rate", type=float, default=250.0)
    parser.add_argument("--seconds", type=float, default=3.0)
    D.add_emulator_nice(parser)
    D.add_settings(parser)
    args = parser.parse_args(argv)
    extra = D.settings(args)
    emulators = D.demote_emulators(args.emulator_nice)
    tmp = tempfile.TemporaryDirectory()
    head = D.patient_head(Path(tmp.name) / "head" / "head.toml")
    frame = {"op": "stream", "id": 1, "channels": ["jaw"], "frames": [[0.0, 1.0]]}
    base = bare_push_pull(max(200, args.trials), frame)
    base_rate = bare_router_rate(args.seconds)
    # The jitter buffer's delay is part of the measured latency: 1 ms here (default 50 ms).
    steady: dict[bool, list[float]] = {}
    late: dict[bool, dict[str, Any]] = {}
    for lock in (False, True):
        daemon = D.make_daemon(args.rate, True, head_path=head,
                             **{"runtime.stream_delay_s": 0.001, "runtime.stream_phase_lock": lock, **extra})
        try:
            time.sleep(0.5)
            steady[lock], late[lock] = steady_latency(daemon, args.rate, max(20, args.trials // 4), seed=2)
        finally:
            daemon.stop()
    daemon = D.make_daemon(args.rate, True, head_path=head, **{"runtime.stream_delay_s": 0.001, **extra})
    try:
        lat = stream_latency(daemon, args.trials)
        tp1 = throughput(daemon, args.seconds, 1)
        tp10 = throughput(daemon, args.seconds, 10)
        status = daemon.lifecycle
    finally:
        daemon.stop()
    b50, b99 = D.pct(base, 50) * 1e6, D.pct(base, 99) * 1e6
    l50, l99 = D.pct(lat, 50) * 1e6, D.pct(lat, 99) * 1e6
    period = 1e6 / args.rate
    print(f"{emulators}; settings {extra or 'default'}; load average {os.getloadavg()[0]:.1f} at the end")
    print(f"baseline PUSH->PULL one way: p50 {b50:.0f} us, p99 {b99:.0f} us")
    s50, s99 = D.pct(steady[True], 50) * 1e6, D.pct(steady[True], 99) * 1e6
    u50, u99 = D.pct(steady[False], 50) * 1e6, D.pct(steady[False], 99) * 1e6
    print(f"steady {args.rate:g} Hz stream, frame arrival -> bus write, phase lock on ({len(steady[True])} steps): "
          f"p50 {s50:.0f} us, p99 {s99:.0f} us  (goal p99 <= 2000 us); frames late (lost) "
          f"{late[True]['late']} of {late[True]['replies']} ({late[True]['sender']})")
    print(f"  same stream, phase lock off ({len(steady[False])} steps): p50 {u50:.0f} us, p99 {u99:.0f} us  "
          f"(lock on / off: p99 x{s99 / u99:.2f}); frames late {late[False]['late']} of {late[False]['replies']}")
    print(f"single frames at random phases, arrival -> bus write at {args.rate:g} Hz ({len(lat)}/{args.trials} "
          f"trials): p50 {l50:.0f} us, p99 {l99:.0f} us  (x{l50 / b50:.1f} / x{l99 / b99:.1f} baseline; loop period "
          f"{period:.0f} us: p99 = {l99 / period:.2f} periods)")
    print(f"baseline DEALER->ROUTER echo: {base_rate:.0f} requests/s")
    print(f"stream requests, 1 frame each: {tp1[0]:.0f} frames/s accepted ({tp1[0] / base_rate:.2f} x baseline "
          f"requests/s), {tp1[1]:.0f} late/s")
    print(f"stream requests, 10 frames each: {tp10[0]:.0f} frames/s accepted, {tp10[1]:.0f} late/s   [{status}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
