"""Motion shaping cost per control cycle for the sample head's 13 actuators: ruckig ``Shaper.step`` vs the current
``SafetyFilter.step`` (second-order rate limiter), measured in the same run.

Three target patterns, each played through both shapers with their calls interleaved (one call each in turn) so a
busy machine slows them alike: a stream (every actuator's target moves every cycle, as a curve or a streamed frame
does: the shaper replans every cycle), steps (new random targets every 50 cycles), and holding still. Figures are
p50/p99 per step, in the thread's CPU time (what the step costs) and in wall time (what the loop waited, including
preemption on a busy machine). Budget for ruckig: p99 ≤ 30 µs.

Run: ``python benchmarks/shaper.py [--cycles 20000] [--rate 250]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.headspec import load_head
from runtime.safety import VELOCITY_MARGIN, SafetyFilter
from runtime.shaper import Shaper

HEAD = Path(__file__).resolve().parents[1] / "heads" / "sample" / "head.toml"
BUDGET_P99_S = 30e-6


def targets(pattern: str, cycles: int, lo: np.ndarray, hi: np.ndarray, dt: float, seed: int = 0) -> np.ndarray:
    """(cycles, N) targets inside [lo, hi] for one pattern."""
    rng = np.random.default_rng(seed)
    n = lo.size
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    if pattern == "stream":
        t = np.arange(cycles)[:, None] * dt
        freq = rng.uniform(0.2, 1.5, n)
        phase = rng.uniform(0, 2 * np.pi, n)
        return mid + 0.8 * half * np.sin(2 * np.pi * freq * t + phase)
    if pattern == "steps":
        steps = rng.uniform(lo, hi, size=(cycles // 50 + 1, n))
        return np.repeat(steps, 50, axis=0)[:cycles]
    return np.tile(mid, (cycles, 1))


def percentiles(ts: np.ndarray) -> tuple[float, float]:
    p50, p99 = np.percentile(ts, [50, 99])
    return float(p50), float(p99)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=20_000)
    ap.add_argument("--rate", type=float, default=250.0, help="control rate, Hz")
    args = ap.parse_args(argv)
    head = load_head(HEAD)
    dt = 1.0 / args.rate
    neutral = np.array([a.neutral for a in head.actuators])
    print(f"{len(head.actuators)} actuators at {args.rate:g} Hz, {args.cycles} cycles per pattern; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; µs per step")
    print(f"{'pattern':>8} {'':>6} {'ruckig p50':>10} {'p99':>7} {'filter p50':>10} {'p99':>7} {'p50 ratio':>9} "
          f"{'p99 ratio':>9}")
    worst_p99 = 0.0
    for pattern in ("stream", "steps", "hold"):
        shaper = Shaper.from_head(head, dt, velocity_margin=VELOCITY_MARGIN)
        shaper.reset(neutral)
        safety = SafetyFilter(head)
        safety.reset(dict(zip(head.actuator_names, neutral, strict=True)))
        x = targets(pattern, args.cycles, shaper.lo, shaper.hi, dt)
        cpu = np.empty((args.cycles, 2))
        wall = np.empty((args.cycles, 2))
        for i in range(args.cycles):
            row = x[i]
            w0, c0 = time.perf_counter(), time.thread_time()
            shaper.step(row, 1.0)
            w1, c1 = time.perf_counter(), time.thread_time()
            safety.step(row, dt, 1.0)
            w2, c2 = time.perf_counter(), time.thread_time()
            cpu[i] = c1 - c0, c2 - c1
            wall[i] = w1 - w0, w2 - w1
        for label, ts in (("cpu", cpu), ("wall", wall)):
            r50, r99 = percentiles(ts[:, 0])
            f50, f99 = percentiles(ts[:, 1])
            if label == "cpu":
                worst_p99 = max(worst_p99, r99)
            print(f"{pattern:>8} {label:>6} {r50 * 1e6:>10.1f} {r99 * 1e6:>7.1f} {f50 * 1e6:>10.1f} {f99 * 1e6:>7.1f} "
                  f"{r50 / f50:>9.2f} {r99 / f99:>9.2f}")
    verdict = "within" if worst_p99 <= BUDGET_P99_S else "over"
    print(f"ruckig worst p99 (CPU time) {worst_p99 * 1e6:.1f} µs: {verdict} the {BUDGET_P99_S * 1e6:.0f} µs budget; "
          f"load average now {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
