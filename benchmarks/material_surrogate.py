"""Cost and exactness of the material-fit surrogate: closed form versus the FEM virtual test, same curve.

For frictionless grips the homogeneous closed form is the FEM answer; this prints, measured in one run, the time
of one force-strain curve by each, their ratio, and the largest relative difference between the two curves.
Run: ``python benchmarks/material_surrogate.py [--points 15] [--repeat 20]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> int:
    """Time both forward models on the default -20…+50 % curve and print the ratio."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=15, help="strain points on -0.2..0.5 (default 15)")
    parser.add_argument("--repeat", type=int, default=20, help="closed-form repetitions (default 20)")
    args = parser.parse_args()

    from offline.material.fit import closed_form_forces
    from offline.material.models import MaterialParams
    from offline.material.specimen import make_plan
    from offline.material.virtual_test import run_plan

    params = MaterialParams("neohookean", 78_000.0, 0.47)
    plan = make_plan("auto")
    strain = np.round(np.linspace(-0.2, 0.5, args.points), 12)
    run_plan(params, plan, strain[:2], grips="frictionless")  # JIT warm-up

    t0 = time.perf_counter()
    fem = run_plan(params, plan, strain, grips="frictionless")
    t_fem = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(args.repeat):
        cf = closed_form_forces(params, strain, plan)
    t_cf = (time.perf_counter() - t0) / args.repeat
    moved = strain != 0.0
    diff = float(np.max(np.abs(fem[moved] / cf[moved] - 1.0)))
    t0 = time.perf_counter()
    clamped = run_plan(params, plan, strain, grips="clamped")
    t_clamped = time.perf_counter() - t0
    print(f"curve of {strain.size} strains, {params.model} E={params.E:g} Pa nu={params.nu}")
    print(f"  closed form             {t_cf * 1e3:9.3f} ms")
    print(f"  FEM frictionless grips  {t_fem * 1e3:9.1f} ms   ratio FEM/closed form = {t_fem / t_cf:8.0f}x")
    print(f"  FEM clamped grips       {t_clamped * 1e3:9.1f} ms   ratio FEM/closed form = {t_clamped / t_cf:8.0f}x")
    print(f"  max |FEM/closed form - 1| (frictionless) = {diff:.2e}")
    print(f"  clamped/frictionless force at -20 % and +50 %: {clamped[0] / fem[0]:.3f}, {clamped[-1] / fem[-1]:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
