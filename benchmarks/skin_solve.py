"""ARKit frame solve including the reduced strain guard, vs the previous implementation measured in the same run.

Frames: the sample head's ``blendshapes.json`` performance sampled at 500 Hz (warm-started frame to frame, as the
daemon solves it) and random sparse face-unit weights. Per frame, interleaved so machine load hits both alike:

* core (new): ``KsnnInverse.solve`` (52 units, 3 iterations) with the guard's reduced measure of the solution in
  the same compiled call (``measure=``), and its verdict; the goal is p99 ≤ 0.1 ms;
* ``SkinTargetSolver.solve`` (new), the same plus channel parsing and telemetry;
* reference: the previous inverse (``benchmarks/_skin_reference.py``) + the previous guard check (a full predictor
  pass and the extreme strain over all triangles), and one predictor forward pass alone.

Then it prints the agreements stored in the guard's report (``likeness offline guard evaluate``).

Run: ``python benchmarks/skin_solve.py [--random 1000] [--report heads/sample/skin_guard_report.json]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._skin_reference import ReferenceInverse, reference_guard_ok  # noqa: E402
from models.clip import load_clip_file  # noqa: E402
from models.headspec import load_head  # noqa: E402
from runtime.skin import SkinTargetSolver  # noqa: E402

HEAD = ROOT / "heads" / "sample" / "head.toml"
CLIP = ROOT / "heads" / "sample" / "performances" / "blendshapes.json"
REPORT = ROOT / "heads" / "sample" / "skin_guard_report.json"


def frames(solver: SkinTargetSolver, n_random: int, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """(kind, unit weights) per frame: the performance at 500 Hz, then random sparse weights."""
    clip = load_clip_file(CLIP)
    out = []
    for i in range(int(clip.duration * 500) + 1):
        w = np.zeros(len(solver.units))
        for ch, v in clip.sample(i / 500).items():
            j = solver.units.get(ch.removeprefix("arkit."))
            if j is not None:
                w[j] = min(max(v, 0.0), 1.0)
        out.append(("performance", w))
    rng = np.random.default_rng(seed)
    for _ in range(n_random):
        w = rng.uniform(0.0, 0.6, len(solver.units)) * (rng.random(len(solver.units)) < 0.15)
        out.append(("random", w))
    return out


def pct(ts: list[float]) -> tuple[float, float, float]:
    """p50, p99 and p1 (the nearly undisturbed cost on a loaded machine), µs."""
    a = np.asarray(ts) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(np.percentile(a, 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--random", type=int, default=1000, help="random frames after the performance (default 1000)")
    ap.add_argument("--report", default=str(REPORT), help="guard agreement report to print")
    args = ap.parse_args(argv)
    head = load_head(HEAD)
    solver = SkinTargetSolver.from_head(head)
    assert solver is not None
    guard = solver.strain_guard
    inv = solver.inverse
    sp = solver.predictor
    ref = ReferenceInverse(sp.weights, sp.face_unit_offsets, smoothness=inv.smoothness, lo=solver.lo, hi=solver.hi)
    names = [f"arkit.{n}" for n in solver.units]
    fr = frames(solver, args.random)
    times: dict[str, dict[str, list[float]]] = {k: {"core": [], "solver": [], "reference": [], "forward": []}
                                                for k in ("performance", "random")}
    p_new = solver.neutral.copy()
    p_ref = solver.neutral.copy()
    dev = 0.0
    passes = {"new": 0, "reference": 0}
    its, tol, xtol = solver.max_iterations, solver.tol, solver.xtol
    clock = time.perf_counter
    for kind, w in fr:
        t0 = clock()
        res = inv.solve(w, p_prev=p_new, max_iterations=its, tol=tol, xtol=xtol, measure=guard)
        ok_new = guard.passes(res.strain)
        t1 = clock()
        targets = {n: float(x) for n, x in zip(names, w, strict=True) if x > 0}
        t2 = clock()
        solver.solve(targets, {})
        t3 = clock()
        r_ref = ref.solve(w, p_prev=p_ref, max_iterations=its, tol=tol)
        ok_ref = reference_guard_ok(sp, r_ref.p, guard.strain_range)
        t4 = clock()
        sp.predict(r_ref.p)
        t5 = clock()
        tk = times[kind]
        tk["core"].append(t1 - t0)
        tk["solver"].append(t3 - t2)
        tk["reference"].append(t4 - t3)
        tk["forward"].append(t5 - t4)
        dev = max(dev, float(np.abs(res.p - r_ref.p).max()))
        passes["new"] += int(ok_new)
        passes["reference"] += int(ok_ref)
        p_new, p_ref = res.p, r_ref.p
    load = os.getloadavg()
    print(f"skin ARKit frame solve, sample head (52 units, H = 26, {its} iterations/frame, reduced guard: "
          f"{guard.calibration.patches} patches, {guard.calibration.vertices} vertices); load average "
          f"{load[0]:.1f} on {os.cpu_count()} CPUs")
    for kind, tk in times.items():
        c50, c99, c1 = pct(tk["core"])
        s50, s99, _ = pct(tk["solver"])
        r50, r99, r1 = pct(tk["reference"])
        f50, f99, f1 = pct(tk["forward"])
        print(f"  {kind:11s} ({len(tk['core'])} frames)  p50 / p99 µs: core {c50:6.1f} / {c99:6.1f}   "
              f"SkinTargetSolver.solve {s50:6.1f} / {s99:6.1f}   reference {r50:6.1f} / {r99:6.1f}   "
              f"one predictor pass {f50:5.1f} / {f99:5.1f}")
        print(f"  {'':11s} core vs reference: p50 {r50 / c50:.1f}x faster, p99 {r99 / c99:.1f}x; p1 core {c1:.1f}, "
              f"reference {r1:.1f}, predictor pass {f1:.1f} µs; p99 goal 100 µs {'met' if c99 <= 100 else 'NOT met'}")
    print(f"  largest pose difference from the reference solve: {np.degrees(dev):.4f}° (early stop at "
          f"{xtol:g} of the range); unguarded solutions passed by the new guard {passes['new']} of {len(fr)}, by the "
          f"previous one {passes['reference']}")
    rep = Path(args.report)
    if rep.is_file():
        r = json.loads(rep.read_text())
        print(f"  guard report ({rep.name}, {r['poses']} FEM poses): guard vs FEM {r['guard_vs_fem']:.4f}, "
              f"reduced vs full {r['reduced_vs_full']:.4f}, reduced vs FEM {r['reduced_vs_fem']:.4f}")
        for root, d in r.get("per_dataset", {}).items():
            print(f"    {root}: {d['poses']} poses, guard vs FEM {d['guard_vs_fem']:.4f}, reduced vs full "
                  f"{d['reduced_vs_full']:.4f}, FEM passes {d['fem_ok_fraction']:.2f}")
    else:
        print(f"  no guard report at {rep} (likeness offline guard evaluate ... --out {rep})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
