"""Full bus cycles (write targets, read feedback) of both drivers against their emulators, in one process and across
processes, as ratios to the physical bus time of the same cycle (CAN at 1 Mbit/s; Dynamixel at 4 and 1 Mbaud).

Run: ``python benchmarks/bus_cycle.py [--motors 13 40] [--cycles 300]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import _bus_canopen, _bus_dynamixel  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--motors", type=int, nargs="+", default=[13, 40])
    parser.add_argument("--cycles", type=int, default=300)
    args = parser.parse_args(argv)
    for n in args.motors:
        can = _bus_canopen.measure(n, args.cycles)
        wire = can["can_1mbit"]["cycle_s_worst_stuffing"]
        for transport in ("virtual", "socketcand"):
            r = can[transport]
            print(f"canopen402 {n:3d} drives  {transport:<17} median {r['median_s'] * 1e3:7.3f} ms  p99 "
                  f"{r['p99_s'] * 1e3:7.3f} ms  CAN wire {wire * 1e3:6.3f} ms  ratio {r['ratio_to_can']:6.2f} "
                  f"(p99 {r['p99_ratio_to_can']:6.2f})", flush=True)
        dxl = _bus_dynamixel.measure(n, args.cycles)
        for r in dxl["rows"]:
            print(f"dynamixel  {n:3d} servos  {r['transport']:<17} median {r['median_s'] * 1e3:7.3f} ms  p99 "
                  f"{r['p99_s'] * 1e3:7.3f} ms  wire@4M {r['budget_s'] * 1e3:6.3f} ms  ratio {r['ratio']:6.2f} "
                  f"(vs 1M {r['ratio_1M']:5.2f})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
