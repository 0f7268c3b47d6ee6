"""Benchmark: thickness optimization formulations on the same ground-truth block problems, same run.

For each seed, the block recovery (``offline.design.ground_truth``) is solved by the adjoint formulation with
Gauss-Newton steps (the baseline), the adjoint formulation with L-BFGS steps, and the joint Gauss-Newton
formulation. Prints wall time and its ratio to the baseline, iterations, pose solves, the worst relative height
error and the worst surface error. Also times, at the uniform start, one forward evaluation (every pose solved to
equilibrium, warm-started) against one adjoint gradient (factor K_ff per pose, one solve each).
Run: ``python benchmarks/thickness_methods.py [--quick] [--seeds 0 1 2]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from offline.design.ground_truth import BlockSettings, block_problem, run_ground_truth
    from offline.design.thickness import adjoint_gradient, solve_poses
    from offline.fem import kernel_threads

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="test-size block")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    base = BlockSettings.quick() if args.quick else BlockSettings.default()
    with kernel_threads(args.threads):
        run_ground_truth(replace(BlockSettings.quick(), max_iterations=1), seed=0)  # compile the kernels
        problem, _, _ = block_problem(base, seed=args.seeds[0])
        h0 = np.full(base.n_samples, base.size_m[2])
        state = solve_poses(problem, h0)
        reps = 3
        t = time.perf_counter()
        for _ in range(reps):
            solve_poses(problem, h0 * (1 + 1e-4), state.xs)
        t_fwd = (time.perf_counter() - t) / reps
        t = time.perf_counter()
        for _ in range(reps):
            adjoint_gradient(problem, state)
        t_adj = (time.perf_counter() - t) / reps
        print(f"block {base.size_m} m, {base.divisions} divisions, {base.n_samples} samples, {base.n_poses} poses")
        print(f"forward evaluation (all poses, warm start) {t_fwd * 1e3:.1f} ms; adjoint gradient "
              f"{t_adj * 1e3:.1f} ms; ratio adjoint/forward {t_adj / t_fwd:.2f}")
        print(f"{'seed':>4} {'method':>20} {'time s':>8} {'ratio':>6} {'iters':>5} {'solves':>6} "
              f"{'height rel err':>14} {'surface err m':>13}")
        for seed in args.seeds:
            t_base = None
            for method in ("gauss-newton", "lbfgs", "joint"):
                r = run_ground_truth(replace(base, method=method, max_iterations=200 if method == "lbfgs" else 40),
                                     seed=seed)
                t_base = t_base or r["optimize_seconds"]
                print(f"{seed:>4} {r['method']:>20} {r['optimize_seconds']:8.2f} {r['optimize_seconds'] / t_base:6.2f} "
                      f"{r['iterations']:5d} {r['forward_pose_solves']:6d} {r['height_rel_error_max']:14.2e} "
                      f"{r['surface_error_max_m']:13.2e}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
