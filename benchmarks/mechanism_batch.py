"""Tabulating the sample head's mechanism: every pose at once (``Mechanism.link_poses_many``) vs one pose at a time
(``Mechanism.link_poses``, each continued from the previous pose), measured in the same run, with their largest
difference.

This is what ``linkmap_from_mechanism`` (calibration's runtime map of a fitted mechanism, the layout design's map)
and the calibration tests' ground truth do. The emulated sample head (zero errors and hard stops, seed 5) at random
motor vectors within the head's limits; the two paths alternate in rounds so a busy machine slows them alike.

Run: ``python benchmarks/mechanism_batch.py [--poses 300] [--rounds 2]``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.headspec import load_head
from models.mechanism import SAMPLE_MECHANISM
from sim_hardware.mechanism import sample_mechanism

HEAD = Path(__file__).resolve().parents[1] / "heads" / "sample" / "head.toml"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    head = load_head(HEAD)
    names = list(head.actuator_names)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    P = np.random.default_rng(args.seed).uniform(lo, hi, (args.poses, len(names)))
    digest = hashlib.sha256(SAMPLE_MECHANISM.read_bytes()).hexdigest()[:12]
    print(f"{SAMPLE_MECHANISM.name} sha256 {digest}, {args.poses} poses (seed {args.seed}), {args.rounds} rounds; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    one_s, many_s, worst = [], [], 0.0
    for _ in range(args.rounds):
        mech = sample_mechanism(head, seed=5)
        t0 = time.perf_counter()
        many = mech.link_poses_many(names, P)
        t1 = time.perf_counter()
        one = [mech.link_poses(dict(zip(names, p, strict=True))) for p in P]
        t2 = time.perf_counter()
        many_s.append(t1 - t0)
        one_s.append(t2 - t1)
        worst = max(worst, max(float(np.abs(many[n][i] - T[n]).max()) for i, T in enumerate(one) for n in T))
    a, b = min(one_s), min(many_s)
    print(f"one at a time {a:.3f} s, all at once {b:.3f} s (best of {args.rounds}): {a / b:.1f}x; "
          f"largest difference of a pose matrix entry {worst:.2e} (m, or rotation-matrix units)")
    return 0 if worst < 1e-9 else 1


if __name__ == "__main__":
    sys.exit(main())
