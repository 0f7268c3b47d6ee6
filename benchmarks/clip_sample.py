"""Clip sampling per control cycle: ``CompiledClip.sample`` (flat arrays, no per-channel loop) against
``Clip.sample`` (per-channel dicts and bisect) on the same 52-channel, ~10 000-key clip, for step, linear and Bezier
curves (Bezier with the 1/3-span handles animation tools export, and with random handles), p50 / p99 / max per
sample at random times, measured in this run; plus the compiled clip's bytes per key, and for Bezier curves the
compiled kernel (:mod:`models._cycle_kernels`) against the numpy lockstep iteration it replaces.

Run: ``python benchmarks/clip_sample.py [--samples 20000]``.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.clip import Clip, clip_from_dict
from models.kernel_support import kernels_available
from runtime.compiled import compile_clip

CHANNELS = 52
KEYS_PER_CHANNEL = 10_000 // CHANNELS


def make_clip(interp: str, rng: np.random.Generator, handles: str = "tool") -> Clip:
    """52 channels of ~192 keys each at 30 fps-ish random spacing, values in [-30, 30]."""
    channels = {}
    for c in range(CHANNELS):
        t = np.cumsum(rng.uniform(0.02, 0.05, KEYS_PER_CHANNEL))
        v = rng.uniform(-30, 30, KEYS_PER_CHANNEL)
        if interp != "bezier":
            keys = np.column_stack([t, v])
        elif handles == "tool":  # Catmull-Rom-like slopes, handles a third of the neighbouring spans
            slope = np.gradient(v, t)
            span_in = np.diff(t, prepend=t[0] - 0.03) / 3
            span_out = np.diff(t, append=t[-1] + 0.03) / 3
            keys = np.column_stack([t, v, -span_in, -slope * span_in, span_out, slope * span_out])
        else:
            n = len(t)
            keys = np.column_stack([t, v, -rng.uniform(0, 0.05, n), rng.normal(0, 5, n), rng.uniform(0, 0.05, n),
                                    rng.normal(0, 5, n)])
        channels[f"c{c}"] = {"interp": interp, "keys": keys.tolist()}
    return clip_from_dict({"name": f"{interp}-{handles}", "channels": channels})


def percentiles_us(fn, times: np.ndarray) -> tuple[float, float, float]:
    out = np.empty(len(times))
    gc.disable()
    try:
        for k, t in enumerate(times):
            t0 = time.perf_counter_ns()
            fn(t)
            out[k] = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    p50, p99 = np.percentile(out, [50, 99]) / 1e3
    return float(p50), float(p99), float(out.max() / 1e3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=20_000)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {CHANNELS} channels x "
          f"{KEYS_PER_CHANNEL} keys", flush=True)
    for interp, handles in (("step", ""), ("linear", ""), ("bezier", "tool"), ("bezier", "random")):
        clip = make_clip(interp, rng, handles or "tool")
        cc = compile_clip(clip, list(clip.channels))
        out = np.empty(CHANNELS)
        times = rng.uniform(0, clip.duration, args.samples)
        fast = percentiles_us(lambda t, cc=cc, out=out: cc.sample(t, out), times)
        slow = percentiles_us(clip.sample, times[: max(1000, args.samples // 10)])
        print(f"{interp + (' (' + handles + ' handles)' if handles else ''):<26} CompiledClip.sample p50 "
              f"{fast[0]:7.1f} us  p99 {fast[1]:7.1f} us  max {fast[2]:8.1f} us   Clip.sample p50 {slow[0]:7.1f} us "
              f" p99 {slow[1]:7.1f} us   ratio p50 x{slow[0] / fast[0]:.1f}, p99 x{slow[1] / fast[1]:.1f}   "
              f"{cc.nbytes / cc.key_count:.0f} bytes/key", flush=True)
        if interp == "bezier" and kernels_available():  # the compiled kernel against the numpy lockstep iteration
            lock = percentiles_us(lambda t, cc=cc, out=out: cc.sample(t, out, compiled=False), times)
            print(f"{'':<26} numpy lockstep Bezier    p50 {lock[0]:7.1f} us  p99 {lock[1]:7.1f} us  -> compiled kernel"
                  f" ratio p50 x{lock[0] / fast[0]:.1f}, p99 x{lock[1] / fast[1]:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
