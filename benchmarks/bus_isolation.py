"""What the bus libraries cost the control loop: a 500 Hz SCHED_FIFO loop on the sample head's two buses (CiA 402
over socketcand, Dynamixel over a pseudo-terminal; both emulators in child processes), in two configurations
measured in the same run:

(a) ``sync``: the drivers are called in the loop thread (read both buses, write both buses), as today's daemon does;
(b) ``linked``: each bus runs in its own process behind a ``BusProxy``; the loop only takes the latest feedback and
    posts targets.
A third, ``bare``, runs the same loop with no bus at all: what the machine itself costs (other load, stalls).

Each cycle commands a slow sine (±4 degrees, 0.5 Hz) on every actuator from where it stood at enable. Printed per
configuration: missed deadlines, wake-up jitter p50/p99, cycle work p50/p99, feedback age p50/p99 per bus (loop time
minus the stamp of the oldest motor sample of that bus the cycle used); then the ratios sync / linked.
Run: ``python benchmarks/bus_isolation.py [--seconds 10] [--rate 500]``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SAMPLE = ROOT / "heads" / "sample" / "head.toml"
AMPLITUDE = math.radians(4.0)
FREQUENCY_HZ = 0.5


def _run_loop(rate_hz: float, seconds: float, priority: int, buses: list[str],
              cycle: Callable[[float, np.ndarray], None]) -> dict:
    """Run ``cycle(t, ages)`` at ``rate_hz`` for ``seconds`` in a SCHED_FIFO thread (it fills ``ages`` per bus, in
    seconds); loop statistics and feedback ages."""
    from runtime.loop import LoopStats, RateScheduler, drop_realtime, freeze_heap, try_realtime

    period = 1.0 / rate_hz
    n = int(seconds * rate_hz)
    out: dict = {}

    def body() -> None:
        ok, message = try_realtime(priority)
        out["realtime"] = message
        stats = LoopStats(period, window=n + 16)
        ages = np.full((n, len(buses)), np.nan)
        freeze_heap()
        sched = RateScheduler(period, spin=200e-6)
        t0 = time.monotonic()
        errors = 0
        for i in range(n):
            late, missed = sched.wait()
            start = time.monotonic()
            stats.missed += missed
            try:
                cycle(start - t0, ages[i])
            except Exception as exc:  # a bus error must not end the measurement; count it
                errors += 1
                if errors <= 3:
                    out.setdefault("first_errors", []).append(f"{type(exc).__name__}: {exc}")
            stats.add(late, time.monotonic() - start, start)
        if ok:
            drop_realtime()
        out["stats"] = stats.summary()
        out["errors"] = errors
        for j, bus in enumerate(buses):
            good = ages[:, j][np.isfinite(ages[:, j])] * 1e3
            out[f"age_{bus}"] = (float(np.percentile(good, 50)), float(np.percentile(good, 99))) if good.size \
                else (float("nan"), float("nan"))
        worst = np.nanmax(ages, axis=1) * 1e3
        worst = worst[np.isfinite(worst)]
        out["age_p99_ms"] = float(np.percentile(worst, 99)) if worst.size else float("nan")

    thread = threading.Thread(target=body, name="bench-loop")
    thread.start()
    thread.join()
    return out


def _targets(start: np.ndarray, t: float) -> np.ndarray:
    """The commanded pose at loop time ``t``: a sine from the pose held at enable, clipped to the limits.

    ``start`` rows: held pose, lower limits, upper limits. Starting from the held pose keeps the first step small
    whatever the previous run left behind (the drivers' rate check would refuse a jump).
    """
    return np.clip(start[0] + AMPLITUDE * math.sin(2 * math.pi * FREQUENCY_HZ * t), start[1], start[2])


def _start(head, names: list[str], held: np.ndarray) -> np.ndarray:
    acts = [head.actuator(n) for n in names]
    return np.array([held, [a.min for a in acts], [a.max for a in acts]])


def measure_sync(head, motors, options, rate_hz: float, seconds: float, priority: int) -> dict:
    """Configuration (a): both drivers called in the loop thread."""
    from drivers.base import LifecycleState
    from drivers.registry import create_bus

    buses = {b: create_bus(head.buses[b].driver, b, options[b], motors[b]) for b in motors}
    try:
        for bus in buses.values():
            for attempt in range(3):  # emulated buses on a loaded host: an answer can come too late
                try:
                    bus.open()
                    bus.enable()
                    break
                except Exception:
                    bus.close()
                    if attempt == 2:
                        raise
        names = {b: [m.name for m in motors[b]] for b in motors}
        neutral = {}
        for b, bus in buses.items():
            states = bus.read()
            neutral[b] = _start(head, names[b], np.array([states[n].position for n in names[b]]))
        io_us: list[float] = []

        bus_items = list(buses.items())

        def cycle(t: float, ages: np.ndarray) -> None:
            t_io = time.monotonic()
            for j, (_, bus) in enumerate(bus_items):
                if bus.state is LifecycleState.FAULT:
                    continue
                states = bus.read()
                ages[j] = time.monotonic() - min(s.timestamp for s in states.values())
            for b, bus in bus_items:
                if bus.state is LifecycleState.ACTIVE:
                    # the pose of the moment of writing: a read that blocked must not make this step look too fast
                    at = t + time.monotonic() - t_io
                    bus.write(dict(zip(names[b], _targets(neutral[b], at).tolist(), strict=True)))
            io_us.append((time.monotonic() - t_io) * 1e6)

        out = _run_loop(rate_hz, seconds, priority, list(buses), cycle)
        out["io_p50_us"] = float(np.percentile(io_us, 50))
        out["final_states"] = {b: bus.state.value for b, bus in buses.items()}
        return out
    finally:
        for bus in buses.values():
            with contextlib.suppress(Exception):
                bus.close()


def measure_linked(head, motors, options, rate_hz: float, seconds: float, priority: int, bus_priority: int | None
                   ) -> dict:
    """Configuration (b): each bus in its own process behind a BusProxy."""
    from drivers.base import LifecycleState
    from runtime.bus import BusProxy

    links = {b: BusProxy(head.buses[b].driver, b, options[b], motors[b], open_attempts=3,
                         realtime_priority=bus_priority) for b in motors}
    try:
        for link in links.values():
            link.start(60)
        for link in links.values():
            for attempt in range(3):
                try:
                    link.call("enable")
                    break
                except Exception:
                    if attempt == 2:
                        raise
                    link.call("reset")
        neutral = {b: _start(head, list(link.actuators), link.feedback().positions) for b, link in links.items()}
        link_list = list(links.items())

        def cycle(t: float, ages: np.ndarray) -> None:
            for j, (b, link) in enumerate(link_list):
                fb = link.feedback()
                ages[j] = time.monotonic() - fb.stamp
                if fb.state is LifecycleState.ACTIVE:
                    link.post(_targets(neutral[b], t))

        out = _run_loop(rate_hz, seconds, priority, list(links), cycle)
        fbs = {b: link.feedback() for b, link in links.items()}
        # cost of the loop-side calls alone (median of 2000), with the bus processes running
        b, link = link_list[0]
        target = fbs[b].positions.copy()
        for name, call in (("feedback", link.feedback), ("post", lambda: link.post(target))):
            times = np.empty(2000)
            for i in range(times.size):
                t1 = time.perf_counter()
                call()
                times[i] = time.perf_counter() - t1
            out[f"{name}_us"] = float(np.median(times) * 1e6)
        out["io_p50_us"] = float(np.mean([f.io_us for f in fbs.values()]))
        out["final_states"] = {b: f.state.value for b, f in fbs.items()}
        out["reads"] = {b: f.seq for b, f in fbs.items()}
        return out
    finally:
        for link in links.values():
            link.stop()


def measure_bare(head, motors, rate_hz: float, seconds: float, priority: int) -> dict:
    """Reference: the same loop computing the same targets with no bus at all (what the machine itself costs)."""
    names = {b: [m.name for m in motors[b]] for b in motors}
    start = {b: _start(head, names[b], np.array([head.actuator(n).neutral for n in names[b]])) for b in motors}
    sink = {b: np.zeros(len(names[b])) for b in motors}

    def cycle(t: float, ages: np.ndarray) -> None:
        for j, b in enumerate(start):
            sink[b][:] = _targets(start[b], t)
            ages[j] = 0.0

    out = _run_loop(rate_hz, seconds, priority, list(motors), cycle)
    out["final_states"] = {}
    return out


def _row(name: str, r: dict) -> str:
    s = r["stats"]
    return (f"{name:<7} missed {s['missed']:5d}/{s['cycles']:6d}  jitter p50 {s.get('jitter_p50_us', 0):8.1f} us  "
            f"p99 {s.get('jitter_p99_us', 0):9.1f} us  max {s.get('jitter_max_us', 0) / 1e3:6.1f} ms  "
            f"work p50 {s.get('work_p50_us', 0):7.1f} us  "
            f"p99 {s.get('work_p99_us', 0):8.1f} us  feedback age (p50/p99 ms) "
            + " ".join(f"{k[4:]} {v[0]:.2f}/{v[1]:.1f}" for k, v in r.items()
                       if k.startswith("age_") and k != "age_p99_ms")
            + f"  errors {r['errors']}  buses {r['final_states']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds per configuration (default 10)")
    parser.add_argument("--rate", type=float, default=500.0, help="loop rate in Hz (default 500)")
    parser.add_argument("--priority", type=int, default=80, help="SCHED_FIFO priority of the loop (default 80)")
    parser.add_argument("--bus-priority", type=int, default=None,
                        help="SCHED_FIFO priority of the bus processes (default: normal priority)")
    args = parser.parse_args(argv)

    from models.headspec import load_head
    from runtime.hardware import start_emulators

    head = load_head(SAMPLE)
    motors, options, sims = start_emulators(head)
    try:
        load_before = os.getloadavg()
        bare = measure_bare(head, motors, args.rate, args.seconds, args.priority)
        sync = measure_sync(head, motors, options, args.rate, args.seconds, args.priority)
        linked = measure_linked(head, motors, options, args.rate, args.seconds, args.priority, args.bus_priority)
        load_after = os.getloadavg()
    finally:
        for sim in sims.values():
            sim.close()
    print(f"sample head, {args.rate:.0f} Hz, {args.seconds:g} s per configuration; loop: "
          f"{sync.get('realtime', '?')}; load average before/after {load_before[0]:.2f}/{load_after[0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    print(_row("bare", bare))
    print(_row("sync", sync))
    print(_row("linked", linked))
    s, li = sync["stats"], linked["stats"]

    def ratio(a: float, b: float) -> str:
        return f"x{a / b:.1f}" if b > 0 else ("x1.0" if a == 0 else "inf")

    print(f"ratio sync/linked: missed {s['missed']} vs {li['missed']} ({ratio(s['missed'], li['missed'])}), "
          f"jitter p99 {ratio(s.get('jitter_p99_us', 0), li.get('jitter_p99_us', 0))}, "
          f"work p99 {ratio(s.get('work_p99_us', 0), li.get('work_p99_us', 0))}, "
          f"feedback age p99 {ratio(sync['age_p99_ms'], linked['age_p99_ms'])}")
    print(f"loop-side calls (median): BusProxy.feedback {linked['feedback_us']:.1f} us, BusProxy.post "
          f"{linked['post_us']:.1f} us")
    print(f"bus transaction in the bus processes (last, mean of buses) {linked['io_p50_us']:.0f} us; "
          f"reads per bus {linked.get('reads')}; sync I/O per cycle p50 {sync['io_p50_us']:.0f} us")
    for name, r in (("sync", sync), ("linked", linked)):
        for e in r.get("first_errors", []):
            print(f"  {name} error: {e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
