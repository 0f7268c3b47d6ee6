"""Control-loop jitter (wake-up lateness p50/p99/max) and missed deadlines at 250 Hz and 1 kHz, with and without
SCHED_FIFO, for the loop alone (no bus I/O) and on the sample head's emulated buses.

Baseline: the same loop at normal priority, measured in the same run; ratios are normal / realtime.
Run: ``python benchmarks/loop_jitter.py [--seconds 4]``.
"""

from __future__ import annotations

import argparse
import time

try:
    from benchmarks._daemon import make_daemon
except ImportError:  # run as a script
    from _daemon import make_daemon


def measure(rate_hz: float, realtime: bool, with_buses: bool, seconds: float) -> dict:
    """Loop statistics after ``seconds`` of holding still (enabled, commanding every cycle)."""
    daemon = make_daemon(rate_hz, realtime, with_buses)
    try:
        time.sleep(0.3)
        stats_obj = daemon.runner.stats
        stats_obj.reset()
        time.sleep(seconds)
        stats = stats_obj.summary()
        stats["realtime_status"] = daemon.realtime_status
        stats["lifecycle"] = daemon.lifecycle
    finally:
        daemon.stop()
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=4.0, help="seconds per configuration (default 4)")
    args = parser.parse_args(argv)
    rows = []
    for with_buses in (False, True):
        for rate in (250.0, 1000.0):
            pair = {}
            for realtime in (False, True):
                s = measure(rate, realtime, with_buses, args.seconds)
                pair[realtime] = s
                rows.append((with_buses, rate, realtime, s))
                print(f"{'sample head' if with_buses else 'no bus I/O':<12} {rate:6.0f} Hz  "
                      f"{'SCHED_FIFO' if realtime else 'normal':<10}  jitter p50 {s.get('jitter_p50_us', 0):8.1f} us"
                      f"  p99 {s.get('jitter_p99_us', 0):9.1f} us  max {s.get('jitter_max_us', 0):9.1f} us  "
                      f"missed {s['missed']:5d}/{s['cycles']:6d}  work p50 {s.get('work_p50_us', 0):7.0f} us"
                      f"  ({s['lifecycle']})", flush=True)
            n, r = pair[False], pair[True]
            ratio = n.get("jitter_p99_us", 0) / max(r.get("jitter_p99_us", 0), 1e-3)
            print(f"    ratio normal/realtime: p99 jitter x{ratio:.1f}, missed {n['missed']} vs {r['missed']}"
                  f"   [{r['realtime_status']}]", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
