"""The daemon's control loop on the sample head, emulated buses in their own processes, playing a performance:
missed deadlines, wake-up jitter and cycle work at 500 Hz (the goal: 0 missed, jitter p99 ≤ 100 µs) and 1 kHz.

Baseline measured in the same run: the bare loop (the same scheduler and priority, no work) for as long; the
ratio is the daemon's jitter p99 over the bare loop's. Run ``python benchmarks/daemon_loop.py [--rates 500 1000]
[--performance heads/sample/performances/expressive.json]``, with nothing else running (on 2 cores a busy second
core doubles timings).
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np

try:
    from benchmarks._daemon import ROOT, performance_daemon
except ImportError:  # run as a script
    from _daemon import ROOT, performance_daemon


def bare_loop(rate_hz: float, seconds: float) -> dict:
    """The loop scheduler alone, SCHED_FIFO when permitted, on its own thread."""
    from runtime.loop import LoopStats, RateScheduler, drop_realtime, freeze_heap, try_realtime

    period = 1.0 / rate_hz
    stats = LoopStats(period, window=int(rate_hz * seconds) + 16)
    out: dict = {}

    def run() -> None:
        _ok, msg = try_realtime(60)
        out["realtime"] = msg
        freeze_heap()
        sched = RateScheduler(period, 200e-6)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            late, missed = sched.wait()
            t0 = time.monotonic()
            stats.missed += missed
            stats.add(late, time.monotonic() - t0, t0)
        drop_realtime()

    th = threading.Thread(target=run)
    th.start()
    th.join()
    return {**stats.summary(), **out}


def daemon_run(rate_hz: float, performance: Path, extra: dict | None = None) -> dict:
    """Start the daemon, play the performance once, return the loop statistics over the playing time."""
    with performance_daemon(rate_hz, performance, extra) as (daemon, c, reply):
        runner = daemon.runner
        assert runner is not None
        n0, m0 = runner.stats.n, runner.stats.missed
        c.call("play", clip=reply["clip"])
        time.sleep(reply["duration"] + 0.2)
        stats = runner.stats
        k = stats.n - n0
        idx = (np.arange(stats.n - k, stats.n)) % stats.window
        lat = np.abs(stats.lateness[idx]) * 1e6
        work = stats.work[idx] * 1e6
        status = c.call("status")
        return {"cycles": k, "missed": stats.missed - m0, "jitter_p50_us": float(np.percentile(lat, 50)),
                "jitter_p99_us": float(np.percentile(lat, 99)), "jitter_max_us": float(lat.max()),
                "work_p50_us": float(np.percentile(work, 50)), "work_p99_us": float(np.percentile(work, 99)),
                "lifecycle": status["lifecycle"], "realtime": daemon.realtime_status,
                "feedback_age_s": status.get("feedback_age_s"), "window_truncated": k > stats.window}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rates", type=float, nargs="+", default=[500.0, 1000.0])
    parser.add_argument("--performance", type=Path,
                        default=ROOT / "heads" / "sample" / "performances" / "expressive.json")
    parser.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                        help="a config override, e.g. runtime.bus_priority=0 (TOML value)")
    args = parser.parse_args(argv)
    import tomllib

    extra = {k: tomllib.loads(f"v = {v}")["v"] for k, v in (item.split("=", 1) for item in args.set)}
    for rate in args.rates:
        d = daemon_run(rate, args.performance, extra)
        seconds = d["cycles"] / rate
        b = bare_loop(rate, seconds)
        ratio = d["jitter_p99_us"] / max(b["jitter_p99_us"], 1e-3)
        print(f"{rate:6.0f} Hz daemon ({args.performance.name}, {d['cycles']} cycles): missed {d['missed']}, "
              f"jitter p50 {d['jitter_p50_us']:.1f} us p99 {d['jitter_p99_us']:.1f} us max {d['jitter_max_us']:.0f} us,"
              f" work p50 {d['work_p50_us']:.0f} us p99 {d['work_p99_us']:.0f} us  [{d['lifecycle']}; "
              f"{d['realtime']}]", flush=True)
        print(f"        bare loop ({b['cycles']} cycles): missed {b['missed']}, jitter p99 {b['jitter_p99_us']:.1f} us"
              f"  -> daemon/bare jitter p99 x{ratio:.2f}; feedback age {d['feedback_age_s']}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
