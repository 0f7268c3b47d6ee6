"""Full read + write cycle of the motor drivers against the emulators, 13 and 40 motors per backend.

Prints median and p99 cycle times and the ratio to each bus's physical budget (the time the same
traffic needs on the wire), so a ratio near 1 means the software keeps up with the real bus.
Usage: ``python benchmarks/bus_cycle.py [--cycles N] [--motors 13 40] [--backend canopen dynamixel]``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BACKENDS = {"canopen": "benchmarks._bus_canopen", "dynamixel": "benchmarks._bus_dynamixel"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=500)
    parser.add_argument("--motors", type=int, nargs="+", default=[13, 40])
    parser.add_argument("--backend", nargs="+", choices=sorted(BACKENDS), default=sorted(BACKENDS))
    args = parser.parse_args()
    rows = []
    for backend in args.backend:
        module = importlib.import_module(BACKENDS[backend])
        for n in args.motors:
            result = module.measure(n, args.cycles)
            results = result if isinstance(result, list) else result.get("rows", [result])
            for r in results:
                rows.append((backend, n, r))
    print(f"{'backend':<10} {'motors':>6} {'transport':<14} {'median ms':>10} {'p99 ms':>9} "
          f"{'budget ms':>10} {'ratio':>7}")
    for backend, n, r in rows:
        print(
            f"{backend:<10} {n:>6} {r.get('transport', '-'):<14} {r['median_s'] * 1e3:>10.3f} "
            f"{r['p99_s'] * 1e3:>9.3f} {r['budget_s'] * 1e3:>10.3f} {r['median_s'] / r['budget_s']:>7.2f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
