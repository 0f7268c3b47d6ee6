"""Benchmark: quasi-static indentation of a silicone slab, offline.fem against SfePy (and felupe), same run.

A box slab (63,000 linear tets for ``--size full``, 5,040 for ``--size small``) has its bottom clamped and a central
patch of its top (half the slab's width and depth) pushed down by 10 % of the thickness, x/y held. Material:
compressible neo-Hookean Ψ = μ/2 (J^(-2/3) tr C − 3) + κ/2 (J − 1)², μ = 30 kPa, κ = 300 kPa.

Each solver runs in its own fresh process (so peak RSS is its own): offline.fem (auto backend), SfePy
(``dw_tl_he_neohook`` + ``dw_tl_bulk_penalty``, Newton + PyPardiso, time-stepped load), felupe (``NeoHooke(mu,
bulk)``, Newton + ``pypardiso.spsolve``). SfePy's terms define S = μ J^(-2/3)(I − tr C C⁻¹/3) and
S = κ (J − 1) J C⁻¹, i.e. exactly the energy above (checked in their docstrings, and by the displacement agreement
printed here); felupe's NeoHooke with ``bulk`` is the same energy. All use the same residual threshold (N).

Prints wall times (setup and solve), the time ratio peer / ours, our per-phase breakdown, the numbers of numeric
factorizations and preconditioned CG iterations, peak RSS, and the max difference in displacements against ours;
then one ``RATIO`` line: felupe-sym's solve time over ours (wall clock; process CPU time too, which a loaded machine
disturbs less). Run: ``python benchmarks/fem_solve.py [--size small|full]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SIZES = {
    "full": ((0.10, 0.07, 0.012), (50, 35, 6)),  # 63,000 tets, 12,852 nodes
    "small": ((0.10, 0.07, 0.012), (20, 14, 3)),  # 5,040 tets, 1,260 nodes
}
MU, KAPPA = 3.0e4, 3.0e5


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _problem(size: str, depth_frac: float):
    """Mesh arrays, the clamped bottom nodes, the indented patch nodes and the indentation depth."""
    sys.path.insert(0, str(ROOT))
    from offline.fem import box_mesh

    dims, div = SIZES[size]
    mesh = box_mesh(dims, div)
    X = np.asarray(mesh.nodes)
    top = np.asarray(mesh.node_sets["z1"])
    c = np.array(dims[:2]) / 2
    half = np.array(dims[:2]) / 4 + 1e-12
    patch = top[np.all(np.abs(X[top, :2] - c) <= half, axis=1)]
    return mesh, np.asarray(mesh.node_sets["z0"]), patch, depth_frac * dims[2]


# ----------------------------------------------------------------------------------------------- solvers (children)


def run_ours(size: str, depth_frac: float, backend: str, tol: float, reuse: bool = True,
             precision: str = "double") -> dict:
    from offline.fem import Dirichlet, SolverOptions, box_mesh, combine, fixed, neo_hookean, prepare, solve_static

    mat = neo_hookean(MU, KAPPA)
    warm = box_mesh((0.01, 0.01, 0.01), (2, 2, 2))  # load the cached numba kernels and the solver libraries
    solve_static(warm, mat, fixed(warm, "z0"), options=SolverOptions(backend=backend, gravity=(0, 0, -9.81)))
    t0 = time.perf_counter()
    mesh, _bottom, patch, depth = _problem(size, depth_frac)
    X = np.asarray(mesh.nodes)
    bc = combine(Dirichlet(patch, X[patch] + [0.0, 0.0, -depth]), fixed(mesh, "z0"))
    prepare(mesh)  # per-mesh geometry and CSR pattern, as the peers build theirs during setup
    rss0 = _rss_mb()
    t1, c1 = time.perf_counter(), time.process_time()
    opts = SolverOptions(backend=backend, tol_force=tol, reuse_factorization=reuse, factor_precision=precision)
    res = solve_static(mesh, mat, bc, options=opts)
    t2, c2 = time.perf_counter(), time.process_time()
    from offline.fem.linsolve import resolve_backend

    on_patch = np.isin(bc.nodes, patch)
    name = f"offline.fem ({resolve_backend(backend)}{'' if reuse else ', exact Newton'}" \
           f"{', float32 factor' if precision == 'single' else ''})"
    return {"name": name, "setup_s": t1 - t0, "solve_s": t2 - t1, "cpu_s": c2 - c1,
            "u": res.x - X, "iterations": res.iterations, "load_steps": res.load_steps,
            "timings": dict(res.timings), "rss_before_mb": rss0, "rss_peak_mb": _rss_mb(),
            "threshold": res.log[-1]["tolerance"], "residuals": [e["residual"] for e in res.log],
            "patch_force": float(res.reactions[on_patch, 2].sum()), "factorizations": res.factorizations,
            "krylov_iterations": res.krylov_iterations, "reuse": reuse}


def run_sfepy(size: str, depth_frac: float, n_steps: int, threshold: float) -> dict:
    from sfepy.base.base import output
    from sfepy.discrete import Equation, Equations, FieldVariable, Function, Integral, Material, Problem
    from sfepy.discrete.conditions import Conditions, EssentialBC
    from sfepy.discrete.fem import FEDomain, Field, Mesh
    from sfepy.solvers.ls import PyPardisoSolver
    from sfepy.solvers.nls import Newton
    from sfepy.solvers.ts_solvers import SimpleTimeSteppingSolver
    from sfepy.terms import Term

    output.set_output(quiet=True)
    t0 = time.perf_counter()
    mesh, bottom, patch, depth = _problem(size, depth_frac)
    X = np.asarray(mesh.nodes)
    tets = np.asarray(mesh.tets).astype(np.int32)
    smesh = Mesh.from_data("slab", X, None, [tets], [np.zeros(len(tets), np.int32)], ["3_4"])
    domain = FEDomain("domain", smesh)
    omega = domain.create_region("Omega", "all")
    funs = {"get_bottom": lambda coors, domain=None: bottom, "get_patch": lambda coors, domain=None: patch}
    r_bot = domain.create_region("Bottom", "vertices by get_bottom", "vertex",
                                 functions={"get_bottom": Function("get_bottom", funs["get_bottom"])})
    r_patch = domain.create_region("Patch", "vertices by get_patch", "vertex",
                                   functions={"get_patch": Function("get_patch", funs["get_patch"])})
    field = Field.from_args("displacement", np.float64, "vector", omega, approx_order=1)
    u = FieldVariable("u", "unknown", field)
    v = FieldVariable("v", "test", field, primary_var_name="u")
    solid = Material("solid", mu=MU, K=KAPPA)
    integral = Integral("i", order=1)
    t_iso = Term.new("dw_tl_he_neohook(solid.mu, v, u)", integral, omega, solid=solid, v=v, u=u)
    t_vol = Term.new("dw_tl_bulk_penalty(solid.K, v, u)", integral, omega, solid=solid, v=v, u=u)
    eqs = Equations([Equation("balance", t_iso + t_vol)])
    pb = Problem("indentation", equations=eqs)

    def press(ts, coors, **kwargs):
        val = np.zeros((len(coors), 3))
        val[:, 2] = -depth * ts.time
        return val

    ebcs = Conditions([EssentialBC("fix", r_bot, {"u.all": 0.0}),
                       EssentialBC("press", r_patch, {"u.all": Function("press", press)})])
    pb.set_bcs(ebcs=ebcs)
    ls = PyPardisoSolver({})
    status: dict = {}
    nls = Newton({"i_max": 20, "eps_a": threshold, "eps_r": 1.0, "eps_mode": "and"}, lin_solver=ls,
                 status=status)
    tss = SimpleTimeSteppingSolver({"t0": 0.0, "t1": 1.0, "n_step": n_steps + 1, "quasistatic": True},
                                   nls=nls, context=pb, verbose=False)
    pb.set_solver(tss)
    rss0 = _rss_mb()
    t1 = time.perf_counter()
    state = pb.solve(save_results=False)
    t2 = time.perf_counter()
    uu = state.get_state_parts()["u"].reshape(-1, 3)
    return {"name": f"SfePy ({n_steps} load steps, pypardiso)", "setup_s": t1 - t0, "solve_s": t2 - t1, "u": uu,
            "iterations": status.get("n_iter", -1), "load_steps": n_steps, "rss_before_mb": rss0,
            "rss_peak_mb": _rss_mb(), "converged": status.get("condition", 1) == 0,
            "final_residual": status.get("err", float("nan"))}


def _symmetric_pardiso():
    """felupe's best solver here: symmetric positive definite PARDISO on the upper triangle, its symbolic analysis
    kept across Newton iterations (offline.fem's own PARDISO wrapper, so both sides use the same linear solver)."""
    from offline.fem.linsolve import make_solver

    solver = make_solver("pardiso")

    def solve(A, b):
        return solver.factor(A).solve(np.asarray(b).ravel())

    return solve


def run_felupe_sym(size: str, depth_frac: float, threshold: float) -> dict:
    return run_felupe(size, depth_frac, threshold, symmetric=True)


def run_felupe(size: str, depth_frac: float, threshold: float, symmetric: bool = False) -> dict:
    import felupe as fem
    import pypardiso

    t0 = time.perf_counter()
    mesh, bottom, patch, depth = _problem(size, depth_frac)
    X = np.asarray(mesh.nodes)
    fmesh = fem.Mesh(X.copy(), np.asarray(mesh.tets).copy(), "tetra")
    region = fem.RegionTetra(fmesh)
    field = fem.FieldContainer([fem.Field(region, dim=3)])
    m_bot = np.zeros(len(X), bool)
    m_bot[bottom] = True
    m_patch = np.zeros(len(X), bool)
    m_patch[patch] = True
    bounds = {
        "bottom": fem.Boundary(field[0], mask=m_bot),
        "patch_xy": fem.Boundary(field[0], mask=m_patch, skip=(0, 0, 1)),
        "patch_z": fem.Boundary(field[0], mask=m_patch, skip=(1, 1, 0), value=-depth),
    }
    dof0, dof1 = fem.dof.partition(field, bounds)
    ext0 = fem.dof.apply(field, bounds, dof0)
    solid = fem.SolidBody(fem.NeoHooke(mu=MU, bulk=KAPPA), field)
    rss0 = _rss_mb()
    t1, c1 = time.perf_counter(), time.process_time()
    solver = _symmetric_pardiso() if symmetric else pypardiso.spsolve
    res = fem.newtonraphson(field, items=[solid], dof1=dof1, dof0=dof0, ext0=ext0, solver=solver,
                            tol=1e-6, verbose=0)
    t2, c2 = time.perf_counter(), time.process_time()
    name = "felupe (1 step, symmetric PARDISO)" if symmetric else "felupe (1 load step, pypardiso.spsolve)"
    return {"name": name, "setup_s": t1 - t0, "solve_s": t2 - t1, "cpu_s": c2 - c1,
            "u": np.asarray(field[0].values).reshape(-1, 3).copy(), "iterations": int(res.iterations),
            "load_steps": 1, "rss_before_mb": rss0, "rss_peak_mb": _rss_mb(), "converged": bool(res.success)}


def _child(fn_name: str, args: tuple, queue) -> None:
    sys.path.insert(0, str(ROOT))
    try:
        queue.put(globals()[fn_name](*args))
    except BaseException as exc:  # report any failure to the parent instead of hanging it
        queue.put({"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()})


def _in_process(fn_name: str, *args, timeout: float = 1800.0) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(fn_name, args, q))
    p.start()
    try:
        out = q.get(timeout=timeout)
    except Exception as exc:
        out = {"error": f"no result ({type(exc).__name__})"}
    p.join(timeout=30)
    if p.is_alive():
        p.kill()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=sorted(SIZES), default="full")
    ap.add_argument("--depth", type=float, default=0.10, help="indentation depth as a fraction of the thickness")
    ap.add_argument("--backend", default="auto", help="offline.fem linear solver backend")
    ap.add_argument("--sfepy-steps", type=int, default=4, help="SfePy load steps (it fails with 1 at 10 %%)")
    ap.add_argument("--peers", default="sfepy,felupe,felupe-sym",
                    help="comma-separated peers to run (sfepy, felupe, felupe-sym: felupe with symmetric PARDISO)")
    ap.add_argument("--tol", type=float, default=1e-6, help="offline.fem relative force tolerance")
    ap.add_argument("--factor-precision", choices=("double", "single"), default="double",
                    help="offline.fem factorization precision (single: float32 PARDISO factor as a preconditioner)")
    ap.add_argument("--exact-newton", action="store_true",
                    help="also run offline.fem with reuse_factorization=False (one factorization per iteration)")
    args = ap.parse_args(argv)
    peers = [p for p in args.peers.split(",") if p]

    mesh, _, patch, depth = _problem(args.size, args.depth)
    print(f"slab {SIZES[args.size][0]} m, {mesh.n_tets} tets, {mesh.n_nodes} nodes, {3 * mesh.n_nodes} DoFs; "
          f"indentation {depth * 1e3:.2f} mm on {len(patch)} nodes; mu={MU:g} Pa kappa={KAPPA:g} Pa; "
          f"cpus={os.cpu_count()}, load average {os.getloadavg()[0]:.1f}")
    ours = _in_process("run_ours", args.size, args.depth, args.backend, args.tol, True, args.factor_precision)
    if "error" in ours:
        print("offline.fem failed:", ours["error"], ours.get("traceback", ""))
        return 1
    results = [ours]
    thr = ours["threshold"]
    if args.exact_newton:
        results.append(_in_process("run_ours", args.size, args.depth, args.backend, args.tol, False))
    for peer in peers:
        if peer == "sfepy":
            results.append(_in_process("run_sfepy", args.size, args.depth, args.sfepy_steps, thr))
        elif peer == "felupe":
            results.append(_in_process("run_felupe", args.size, args.depth, thr))
        elif peer == "felupe-sym":
            results.append(_in_process("run_felupe_sym", args.size, args.depth, thr))
        else:
            print(f"unknown peer {peer!r} (known: sfepy, felupe, felupe-sym)")
            return 2

    umax = float(np.abs(ours["u"]).max())
    print(f"\nresidual threshold {thr:.3e} N; our residuals: " + ", ".join(f"{r:.2e}" for r in ours["residuals"]))
    print(f"patch reaction (ours) {ours['patch_force']:.4f} N; max |u| {umax * 1e3:.3f} mm\n")
    hdr = f"{'solver':44s} {'setup s':>8s} {'solve s':>8s} {'ratio':>6s} {'steps':>5s} {'iters':>5s} " \
          f"{'RSS MB':>7s} {'+solve':>7s} {'max|du| m':>10s} {'rel':>8s}"
    print(hdr)
    print("-" * len(hdr))
    for r in results:
        if "error" in r:
            print(f"{'(peer failed)':44s} {r['error']}")
            continue
        du = float(np.abs(r["u"] - ours["u"]).max())
        ratio = r["solve_s"] / ours["solve_s"]
        note = "" if r.get("converged", True) else "  NOT CONVERGED"
        print(f"{r['name']:44s} {r['setup_s']:8.2f} {r['solve_s']:8.2f} {ratio:6.2f} {r['load_steps']:5d} "
              f"{r['iterations']:5d} {r['rss_peak_mb']:7.0f} {r['rss_peak_mb'] - r['rss_before_mb']:7.0f} "
              f"{du:10.2e} {du / umax:8.1e}{note}")
    t = ours["timings"]
    print("\noffline.fem phases (s): " + ", ".join(f"{k} {v:.3f}" for k, v in t.items()))
    other = t["total"] - sum(v for k, v in t.items() if k != "total")
    print(f"  (unaccounted: {other:.3f} s: reduced-matrix selector, reactions, bookkeeping)")
    for r in results:
        if "factorizations" in r:
            print(f"{r['name']}: {r['factorizations']} numeric factorizations, {r['krylov_iterations']} "
                  f"preconditioned CG iterations, {r['iterations']} Newton iterations")
    for r in results:
        if r is not ours and "error" not in r and r["name"].startswith("felupe (1 step, symmetric"):
            print(f"RATIO felupe-sym / ours = {r['solve_s'] / ours['solve_s']:.2f} "
                  f"(ours {ours['solve_s']:.2f} s, felupe-sym {r['solve_s']:.2f} s, goal >= 3; "
                  f"load average at end {os.getloadavg()[0]:.1f}); process CPU time ratio "
                  f"{r['cpu_s'] / ours['cpu_s']:.2f} ({ours['cpu_s']:.2f} s vs {r['cpu_s']:.2f} s)")
    print("SfePy's iteration count is that of its last load step.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
