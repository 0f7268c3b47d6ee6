"""Benchmark: face cloning's costs on the sample skin — a pose solve, an adjoint solve, sensitivities, and one outer
iteration (thickness + actuation) with the share of time spent in sparse factorizations.

Targets: the default set's ``jaw_open``, ``smile_left`` and ``blink`` (or ``--targets``), posed at the runtime
predictor's inverse. Per target: a warm-started forward solve after a 1 %-of-range actuation change (what a line
search trial costs), the tangent's assembly and factorization, one adjoint solve (one back-substitution on that
factorization) and the direct sensitivities of all actuators (13 back-substitutions); ratios are to the forward
solve measured in the same run. Then one outer iteration on those targets: one thickness Gauss-Newton iteration
and up to two actuation Gauss-Newton iterations per target, with every factorization timed (offline.fem's Newton
solver, the sensitivities and the adjoint all go through ``make_solver``). Run:
``python benchmarks/clone_iteration.py [--mesh heads/sample/skin] [--targets jaw_open,smile_left,blink]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class _Timer:
    """Accumulates the time spent in factorizations and back-substitutions of every solver made while patched."""

    def __init__(self) -> None:
        self.factor_s = 0.0
        self.solve_s = 0.0
        self.factors = 0

    def wrap(self, make):
        timer = self

        class Fac:
            def __init__(self, fac):
                self.fac = fac
                self.backend = fac.backend

            def solve(self, b):
                t0 = time.perf_counter()
                try:
                    return self.fac.solve(b)
                finally:
                    timer.solve_s += time.perf_counter() - t0

            def __getattr__(self, name):  # everything else of the factorization, untimed
                return getattr(self.fac, name)

        class Solver:
            def __init__(self, inner):
                self.inner = inner
                self.backend = inner.backend

            def factor(self, A):
                t0 = time.perf_counter()
                try:
                    return Fac(self.inner.factor(A))
                finally:
                    timer.factor_s += time.perf_counter() - t0
                    timer.factors += 1

            def __getattr__(self, name):
                return getattr(self.inner, name)

        return lambda backend="auto", precision="double": Solver(make(backend, precision))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "heads" / "sample" / "head.toml"))
    ap.add_argument("--mesh", default=None, help="skin folder (default: the head's skin/)")
    ap.add_argument("--targets", default="jaw_open,smile_left,blink")
    ap.add_argument("--samples", type=int, default=40)
    args = ap.parse_args(argv)

    import offline.design.actuation as act_mod
    import offline.design.thickness as th_mod
    import offline.fem.solve as solve_mod
    from offline.design.actuation import TargetResult, optimize_targets, sensitivities, simulate
    from offline.design.clone import CloneRun, CloneSettings, predictor_inverse
    from offline.design.face import face_warp, load_face
    from offline.design.targets import DEFAULT_TARGETS
    from offline.design.thickness import Pose, ThicknessProblem, optimize_adjoint
    from offline.fem import energy as en
    from offline.fem.linsolve import make_solver
    from offline.fem.solve import SolverOptions

    face = load_face(args.config, args.mesh)
    names = [n.strip() for n in args.targets.split(",") if n.strip()]
    unknown = [n for n in names if n not in DEFAULT_TARGETS]
    if unknown:
        print(f"unknown target(s) {unknown}; known: {', '.join(DEFAULT_TARGETS)}")
        return 2
    settings = CloneSettings(n_samples=args.samples, actuation_iterations=2, thickness_iterations=1)
    run = CloneRun(face, {n: DEFAULT_TARGETS[n] for n in names}, "/nonexistent", settings, progress=lambda s: None)
    problem = run.problem
    print(f"skin {face.mesh.n_nodes} nodes, {face.mesh.n_tets} tets; targets {', '.join(names)}; "
          f"cpus={os.cpu_count()}, load average {os.getloadavg()[0]:.1f} (before)")
    P = predictor_inverse(face, run.unit_names, run.weights)
    if P is None:
        P = [face.space.neutral] * len(names)
    rows = []
    xs = []
    for name, p in zip(names, P, strict=True):
        x = simulate(problem, p)
        dp = p + 0.01 * (face.space.hi - face.space.lo)
        dp = face.space.expand(face.space.project(face.space.reduce(dp)))
        t0 = time.perf_counter()
        simulate(problem, dp, x)
        t_fwd = time.perf_counter() - t0
        t0 = time.perf_counter()
        K = en.stiffness(face.mesh, face.skin.material, x)
        t_asm = time.perf_counter() - t0
        bc = face.space.boundary(p)
        free = np.setdiff1d(np.arange(K.shape[0]), bc.dofs)
        solver = make_solver(problem.solver.backend)
        solver.factor(K[free][:, free].tocsr())  # symbolic analysis once per pattern (reused afterwards)
        t0 = time.perf_counter()
        fac = solver.factor(K[free][:, free].tocsr())
        t_fac = time.perf_counter() - t0
        rhs = np.random.default_rng(0).normal(size=free.size)
        t0 = time.perf_counter()
        fac.solve(rhs)
        t_adj = time.perf_counter() - t0
        t0 = time.perf_counter()
        sensitivities(problem, p, x)
        t_sens = time.perf_counter() - t0
        rows.append((name, t_fwd, t_asm, t_fac, t_adj, t_sens))
        xs.append(x)
    print(f"\n{'target':16s} {'forward s':>9s} {'assemble s':>10s} {'factor s':>9s} {'adjoint s':>9s} "
          f"{'adj/fwd':>8s} {'sens(13) s':>10s} {'sens/fwd':>8s}")
    for name, t_fwd, t_asm, t_fac, t_adj, t_sens in rows:
        print(f"{name:16s} {t_fwd:9.3f} {t_asm:10.4f} {t_fac:9.4f} {t_adj:9.5f} {t_adj / t_fwd:8.4f} "
              f"{t_sens:10.3f} {t_sens / t_fwd:8.3f}")

    timer = _Timer()
    patched = {mod: mod.make_solver for mod in (solve_mod, th_mod, act_mod)}
    for mod, make in patched.items():
        mod.make_solver = timer.wrap(make)
    try:
        t0 = time.perf_counter()
        warp, h0 = face_warp(face, n_samples=settings.n_samples)
        tp = ThicknessProblem(warp, face.skin.material,
                              tuple(Pose(face.space.boundary(p), q) for p, q in zip(P, run.targets, strict=True)),
                              face.outer, settings.h_min, settings.h_max, warp_weight=settings.warp_weight,
                              solver=SolverOptions(tol_force=settings.tol_force, max_iterations=60, load_steps=1))
        t_th0 = time.perf_counter()
        tres = optimize_adjoint(tp, np.clip(h0, settings.h_min + 1e-5, settings.h_max - 1e-5), max_iterations=1,
                                warm=xs)
        t_th = time.perf_counter() - t_th0
        prev = [TargetResult(p, x, 0.0, 0.0, 0, True, 0, [], 0.0) for p, x in zip(P, tres.xs, strict=True)]
        t_a0 = time.perf_counter()
        optimize_targets(problem.with_mesh(warp.rest_mesh(tres.h)), run.targets, previous=prev, max_iterations=2,
                         tol_value=1e-3)
        t_act = time.perf_counter() - t_a0
        total = time.perf_counter() - t0
    finally:
        for mod, make in patched.items():
            mod.make_solver = make
    print(f"\none outer iteration on {len(names)} targets: {total:.1f} s (thickness Gauss-Newton iteration "
          f"{t_th:.1f} s, actuation {t_act:.1f} s); {timer.factors} factorizations {timer.factor_s:.1f} s = "
          f"{timer.factor_s / total:.0%} of the iteration, back-substitutions {timer.solve_s:.1f} s = "
          f"{timer.solve_s / total:.0%}; load average {os.getloadavg()[0]:.1f} (after)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
