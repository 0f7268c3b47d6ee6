"""One FEM pose of the sample head solved from rest, with the indefinite tangent made PSD per quadrature point
(``SolverOptions.psd_projection="quadrature"``, the default) vs per element (``"element"``), measured in the same run.

Far from equilibrium the tangent is indefinite for many Newton iterations, and each projected tangent then costs an
eigen-decomposition per element (30 x 30 on quadratic tets) or per indefinite quadrature point (9 x 9). The poses are
drawn as ``likeness offline dataset`` draws them (full range, a quarter of the values at a range end), solved on the
head's quadratic-tet skin as the shipped dataset was; the two modes alternate pose by pose so a busy machine slows
them alike. Both must converge; the report gives their times, Newton iterations, factorizations and how far apart
the two surfaces are (an equilibrium of a non-convex energy need not be unique: the energies are printed too).

Run: ``python benchmarks/pose_solve.py [--poses 6] [--seed 3] [--element-order 2]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
HEAD = ROOT / "heads" / "sample" / "head.toml"
MODES = ("element", "quadrature")


def main(argv: list[str] | None = None) -> int:
    from models.headspec import load_head
    from offline.dataset.fem_problem import FemSpec, material_fields
    from offline.dataset.sampling import sample_poses
    from offline.fem import solve_static, total_energy
    from offline.fem.warmup import warm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=6)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--boundary-prob", type=float, default=0.25)
    ap.add_argument("--element-order", type=int, default=2, choices=(1, 2))
    args = ap.parse_args(argv)
    head = load_head(HEAD)
    spec = FemSpec(config=str(HEAD), mesh=str(HEAD.parent / "skin"), linkmap=str(HEAD.parent / "linkmap.json"),
                   element_order=args.element_order, **material_fields(head.skin_material()))
    problem = spec.build()
    warm(args.element_order)
    P = sample_poses(head, args.poses, seed=args.seed, boundary_prob=args.boundary_prob)
    digest = hashlib.sha256((HEAD.parent / "skin" / "skin.vtu").read_bytes()).hexdigest()[:12]
    print(f"sample head, skin.vtu sha256 {digest}, element order {args.element_order} ({problem.mesh.n_tets} tets, "
          f"{problem.mesh.n_nodes} nodes); {args.poses} poses (seed {args.seed}, boundary {args.boundary_prob}); "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    totals = dict.fromkeys(MODES, 0.0)
    ok = True
    print(f"{'pose':>4}  {'mode':<10} {'s':>7} {'iters':>5} {'factor':>6} {'steps':>5}  energy J")
    for i, p in enumerate(P):
        bc = problem.dirichlet(p)
        states = {}
        for mode in MODES if i % 2 == 0 else MODES[::-1]:
            opts = dataclasses.replace(problem.options, psd_projection=mode)
            t = time.perf_counter()
            res = solve_static(problem.mesh, problem.material, bc, options=opts)
            dt = time.perf_counter() - t
            totals[mode] += dt
            ok &= bool(res.converged)
            states[mode] = res.x
            energy = total_energy(problem.mesh, problem.material, res.x)
            print(f"{i:>4}  {mode:<10} {dt:7.2f} {res.iterations:5d} {res.factorizations:6d} {res.load_steps:5d}  "
                  f"{energy:.6f}")
        gap = np.linalg.norm(states["element"][problem.outer] - states["quadrature"][problem.outer], axis=1).max()
        print(f"{i:>4}  largest surface distance between the two: {gap * 1e3:.4f} mm")
    ratio = totals["element"] / totals["quadrature"]
    print(f"RATIO element / quadrature = {ratio:.2f} (element {totals['element']:.1f} s, quadrature "
          f"{totals['quadrature']:.1f} s over {args.poses} poses; load average at end {os.getloadavg()[0]:.1f})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
