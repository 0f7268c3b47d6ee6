"""The in-cycle kernels as numba's JIT compiles them and as the loop runs them (compiled ahead of time,
``models.kernels_aot``), on the same arguments in the same run: the ahead-of-time build must not cost the control
cycle time for the memory it saves (``benchmarks/daemon_memory.py``).

Arguments: those the sample head's skin solver and strain guard pass (recorded while ``models.kernels.warm`` runs
them). Each build is called ``--calls`` times after 200 warm-up calls, interleaved in blocks so load hits both alike;
p1 is the nearly undisturbed cost. ``python benchmarks/kernel_builds.py [--calls 3000]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    from models import kernels_aot as KA
    from models.kernels import warm

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--calls", type=int, default=3000)
    args = parser.parse_args(argv)
    head = str(ROOT / "heads" / "sample" / "head.toml")
    warm(head)  # builds the ahead-of-time module where missing
    mod = KA.module()
    if mod is None:
        print("no ahead-of-time build for this machine (numba missing?): nothing to compare")
        return 1
    examples: dict[str, tuple] = {}
    with KA.recording(examples):
        warm(head, ahead_of_time=False)
    print(f"in-cycle kernels, µs per call, {args.calls} calls each; load average {os.getloadavg()[0]:.1f}")
    for name in KA.EXPORTS:
        builds = {"numba JIT": KA.jit(name), "ahead of time": KA.kernel(name)}
        times: dict[str, list[float]] = {b: [] for b in builds}
        for fn in builds.values():
            for _ in range(200):
                fn(*examples[name])
        for _ in range(args.calls // 100):
            for label, fn in builds.items():
                for _ in range(100):
                    t = time.perf_counter()
                    fn(*examples[name])
                    times[label].append(time.perf_counter() - t)
        cells = []
        for label, ts in times.items():
            a = np.array(ts) * 1e6
            cells.append(f"{label} p1 {np.percentile(a, 1):6.2f} p50 {np.percentile(a, 50):6.2f}")
        jit, aot = (np.percentile(np.array(times[b]), 1) for b in builds)
        print(f"  {name:24s} {';  '.join(cells)};  ahead of time / JIT at p1: x{aot / jit:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
