"""ARKit frame solve, as the control core calls it and by name, against the bare compiled call measured in the same run.

Frames: the sample head's ``blendshapes.json`` performance sampled at 500 Hz (warm-started frame to frame, as the
daemon solves it) and random sparse face-unit weights; a channel the frame does not set is NaN. Per frame, each path
on its own solver (the same frames, the same warm-start chain), interleaved so machine load hits them alike, and
each after the same sweep over more memory than a core's cache (as a control cycle runs between other work):

* kernel (the baseline): the bare compiled call (``models._skin_kernels.solve_values_measured``, the build
  ``models.kernels_aot.kernel`` gives the loop: ahead of time where built, else numba's JIT; weights from the
  channel values, the inverse, the guard's reduced measure) with its arguments gathered beforehand, on the array
  path's frame from the same start, keeping its Gauss-Newton matrix across frames as the loop's solve does, and
  the guard's search when the solution leaves the strain range, in the same call;
* kernel, plain G-N: the same call forming JᵀJ in every iteration (``HessianReuse`` with 0 frames), as the solve did
  before it kept the matrix: what keeping it saves;
* kernel, +1 iteration: the same call allowed one more iteration per frame than the head's ``[skin]
  iterations_per_frame``, from the same start: what the cap saves, and (printed after the table) what it costs in
  surface error, and whether a target held for a second frame catches up;
* kernel, exact matrix (a head whose ``[skin] matrix_rank`` is below its predictor's output rank): the same call
  forming the Gauss-Newton matrix from all the residual's rows, on its own kept matrix, from the same start: what the
  lower rank saves, and (printed after the table) what it costs in surface error on the same frames;
* array path: ``SkinTargetSolver.solve_array``, what the core calls every cycle (plus the guard's verdict, the
  warm start and the telemetry figures); the goal is p99 ≤ 0.1 ms;
* mapping API: ``SkinTargetSolver.solve`` from a name → value map (built outside the timing), the same compiled
  call;
* by-name adapter: ``runtime.core.solvers.ArraySolver`` around the mapping API: the core's previous per-cycle path
  (dictionaries both ways), here over the new compiled call;
* reference: the previous inverse (``benchmarks/_skin_reference.py``) + the previous guard check (a full predictor
  pass and the extreme strain over all triangles), and one predictor forward pass alone.

Timings need a quiet machine: on a loaded one read the ratios to the kernel and p1 (the nearly undisturbed cost).
``--profile`` adds a cProfile look at where the array path's and the mapping API's time goes. Then it prints the
agreements stored in the guard's report (``likeness offline guard evaluate``).

Run: ``python benchmarks/skin_solve.py [--random 1000] [--profile] [--report heads/sample/skin_guard_report.json]
[--config HEAD.toml] [--record docs/skin_solve.txt]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._skin_reference import ReferenceInverse, reference_guard_ok  # noqa: E402
from models.clip import load_clip_file  # noqa: E402
from models.headspec import HeadSpec, load_head  # noqa: E402
from models.kernel_args import pack_frame_args  # noqa: E402
from runtime.core.solvers import ArraySolver  # noqa: E402
from runtime.skin import SkinTargetSolver  # noqa: E402

HEAD = ROOT / "heads" / "sample" / "head.toml"
CLIP = ROOT / "heads" / "sample" / "performances" / "blendshapes.json"
REPORT = ROOT / "heads" / "sample" / "skin_guard_report.json"
GOAL_US = 100.0
PATHS = ("kernel", "plain", "more", "exact", "array", "mapping", "adapter", "reference", "forward")


def frames(channels: list[str], n_random: int, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """(kind, channel values in ``channels`` order, NaN: not set) per frame: the performance at 500 Hz, then random
    sparse weights."""
    clip = load_clip_file(CLIP)
    index = {ch: i for i, ch in enumerate(channels)}
    out = []
    for i in range(int(clip.duration * 500) + 1):
        v = np.full(len(channels), np.nan)
        for ch, x in clip.sample(i / 500).items():
            j = index.get(ch)
            if j is not None:
                v[j] = x
        out.append(("performance", v))
    rng = np.random.default_rng(seed)
    n = len(channels)
    for _ in range(n_random):
        out.append(("random", np.where(rng.random(n) < 0.15, rng.uniform(0.0, 0.6, n), np.nan)))
    return out


def stats(ts: list[float]) -> tuple[float, float, float, float]:
    """p50, p99, max and p1 (the nearly undisturbed cost on a loaded machine), µs."""
    a = np.asarray(ts) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max()), float(np.percentile(a, 1))


class Paths:
    """The timed paths, each with its own solver and warm-start chain, run on one frame at a time."""

    def __init__(self, head: HeadSpec) -> None:
        from models.kernels_aot import kernel

        array, mapping, by_name = (SkinTargetSolver.from_head(head) for _ in range(3))
        assert array is not None and mapping is not None and by_name is not None
        self.array, self.mapping = array, mapping
        self.channels = list(self.array.channels())
        self.adapter = ArraySolver(by_name, self.channels, head.actuator_names)
        inv, guard = self.array.inverse, self.array.strain_guard
        self.guard = guard
        self.kernel_fn = kernel("solve_values_measured")  # the code the loop runs (ahead of time where built)
        self.kernel_args = self.array.frame.kernel_args  # the settings the solver's frame solve has bound
        self.kernel_w = np.zeros(inv.n_units)
        self.kernel_p = np.empty(len(self.array.names))
        self.plain_p = np.empty(len(self.array.names))
        n = len(self.array.names)
        self.kernel_reuse = inv.frame_state(self.array.frame.reuse.frames)  # its own kept matrix, as the loop's
        self.plain_reuse = inv.frame_state(0)  # every iteration forms J^T J: the solve before matrices were kept
        self.free_reuse = inv.frame_state(self.array.frame.reuse.frames)
        #: with a Gauss-Newton matrix of lower rank than the residual's: the same call forming the exact matrix
        self.truncated = inv.matrix_rank < inv.rank
        self.exact_args = pack_frame_args(
            (*inv.kernel_arrays(exact_matrix=True), self.array.frame.max_iterations, self.array.frame.tol,
             self.array.frame.xtol), guard.kernel_arrays(),
            None if self.array.frame.guard_steps is None else guard.search_args(self.array.frame.guard_steps))
        self.exact_p = np.empty(n)
        #: the same call with one more iteration per frame, from the same start: what the head's cap costs; and the
        #: kernel's frame held for a second frame at the same values (the cap's shortfall, caught up a frame later?)
        frame = self.array.frame
        self.more_args = pack_frame_args(
            (*inv.kernel_arrays(), frame.max_iterations + 1, frame.tol, frame.xtol), guard.kernel_arrays(),
            None if frame.guard_steps is None else guard.search_args(frame.guard_steps))
        self.more_p = np.empty(n)
        self.held_p = np.empty(n)
        self.more_reuse = inv.frame_state(frame.reuse.frames)
        #: per kind of frame: RMS surface error (m) with the head's iterations, with one more, and held a frame more
        self.iterations_vs_more: dict[str, list[tuple[float, float, float]]] = {"performance": [], "random": []}
        self.exact_reuse = inv.frame_state(self.array.frame.reuse.frames)
        #: per kind of frame: (RMS surface error with the solver's matrix, with the exact one, pose difference)
        self.matrix_vs_exact: dict[str, list[tuple[float, float, float]]] = {"performance": [], "random": []}
        frame = self.array.frame  # the same solve without the guard's search, for the unguarded chain
        self.free_args = pack_frame_args((*inv.kernel_arrays(), frame.max_iterations, frame.tol, frame.xtol),
                                         guard.kernel_arrays())
        self.p_free = self.array.neutral.copy()  # the unguarded chain, compared with the reference's
        sp = self.array.predictor
        self.ref = ReferenceInverse(sp.weights, sp.face_unit_offsets, smoothness=inv.smoothness, lo=self.array.lo,
                                    hi=self.array.hi)
        self.p_ref = self.array.neutral.copy()
        self.q = self.array.neutral.copy()
        self._junk = np.zeros(1 << 18)  # 2 MiB: a core's L2 here
        self.ref_ok = 0
        self.mismatch = 0
        self.dev = 0.0
        self.kept_vs_plain: dict[str, float] = {}  # largest pose difference (rad) per kind of frame
        #: the surface error there (kept, plain): a large difference at equal errors lies along a flat direction
        self.kept_vs_plain_error: dict[str, tuple[float, float]] = {}

    def cool(self) -> None:
        """Other work between two timed calls, as a control cycle has: a sweep over more memory than the core's
        cache holds, so that each timed path starts with its data and code as cold as the others'."""
        np.add(self._junk, 1.0, out=self._junk)

    def run(self, values: np.ndarray, times: dict[str, list[float]], kind: str) -> None:
        """Every path on one frame, each timed after the same :meth:`cool`; the kernel solves the array path's frame
        from the same start. Records whether the array path and the mapping API agree."""
        clock = time.perf_counter
        start = self.array.accepted
        carried = self.kernel_reuse.carry.copy()  # the solution at ``start``, which the other paths start from too
        dt: dict[str, float] = {}
        self.cool()
        t0 = clock()
        self.kernel_fn(values, self.kernel_w, start, self.kernel_p, self.kernel_reuse.matrix, self.kernel_reuse.state,
                       self.kernel_reuse.carry, *self.kernel_args)
        t1 = clock()
        self.cool()
        t2 = clock()
        got, _ = self.array.solve_array(values, self.q)
        t3 = clock()
        dt["kernel"], dt["array"] = t1 - t0, t3 - t2
        self.plain_reuse.carry[:] = carried
        self.cool()
        t0 = clock()
        self.kernel_fn(values, self.kernel_w, start, self.plain_p, self.plain_reuse.matrix, self.plain_reuse.state,
                       self.plain_reuse.carry, *self.kernel_args)
        dt["plain"] = clock() - t0
        self.more_reuse.carry[:] = carried
        self.cool()
        t0 = clock()
        self.kernel_fn(values, self.kernel_w, start, self.more_p, self.more_reuse.matrix, self.more_reuse.state,
                       self.more_reuse.carry, *self.more_args)
        dt["more"] = clock() - t0
        kept = (self.kernel_reuse.matrix.copy(), self.kernel_reuse.state.copy(), self.kernel_reuse.carry.copy())
        self.kernel_fn(values, self.kernel_w, self.kernel_p.copy(), self.held_p, *kept, *self.kernel_args)
        w_units = np.where(np.isfinite(values), np.clip(values, 0.0, 1.0), 0.0)
        inv = self.array.inverse
        self.iterations_vs_more[kind].append(tuple(np.sqrt(inv.surface_error(p.copy(), w_units))
                                                   for p in (self.kernel_p, self.more_p, self.held_p)))
        if self.truncated:
            self.exact_reuse.carry[:] = carried
            self.cool()
            t0 = clock()
            self.kernel_fn(values, self.kernel_w, start, self.exact_p, self.exact_reuse.matrix,
                           self.exact_reuse.state, self.exact_reuse.carry, *self.exact_args)
            dt["exact"] = clock() - t0
            w_units = np.where(np.isfinite(values), np.clip(values, 0.0, 1.0), 0.0)
            inv = self.array.inverse
            self.matrix_vs_exact[kind].append((np.sqrt(inv.surface_error(self.kernel_p.copy(), w_units)),
                                               np.sqrt(inv.surface_error(self.exact_p.copy(), w_units)),
                                               float(np.abs(self.kernel_p - self.exact_p).max())))
        gap = float(np.abs(self.plain_p - self.kernel_p).max())
        if gap >= self.kept_vs_plain.get(kind, 0.0):
            self.kept_vs_plain[kind] = gap
            w_units = np.where(np.isfinite(values), np.clip(values, 0.0, 1.0), 0.0)
            inv = self.array.inverse
            self.kept_vs_plain_error[kind] = (inv.surface_error(self.kernel_p.copy(), w_units),
                                              inv.surface_error(self.plain_p.copy(), w_units))
        targets = {ch: float(v) for ch, v in zip(self.channels, values.tolist(), strict=True) if v == v}
        self.cool()
        t0 = clock()
        res = self.mapping.solve(targets, {})
        t1 = clock()
        self.cool()
        t2 = clock()
        self.adapter.solve_array(values, self.q)
        t3 = clock()
        dt["mapping"], dt["adapter"] = t1 - t0, t3 - t2
        w = np.where(np.isfinite(values), np.clip(values, 0.0, 1.0), 0.0)
        t0 = clock()
        r_ref = self.ref.solve(w, p_prev=self.p_ref, max_iterations=self.array.max_iterations, tol=self.array.tol)
        self.ref_ok += int(reference_guard_ok(self.array.predictor, r_ref.p, self.guard.strain_range))
        t1 = clock()
        self.array.predictor.predict(r_ref.p)
        t2 = clock()
        dt["reference"], dt["forward"] = t1 - t0, t2 - t1
        for name in dt:
            times[name].append(dt[name])
        self.mismatch += int(not np.array_equal(got, [res.actuators[n] for n in self.array.names]))
        free = np.empty_like(self.p_free)
        self.kernel_fn(values, self.kernel_w, self.p_free, free, self.free_reuse.matrix, self.free_reuse.state,
                       self.free_reuse.carry, *self.free_args)
        self.dev = max(self.dev, float(np.abs(free - r_ref.p).max()))
        self.p_free, self.p_ref = free, r_ref.p


def report_times(kind: str, tk: dict[str, list[float]]) -> None:
    """One block of the table: p50 / p99 / max per path, the ratio to the kernel, and the goal."""
    k50, k99, _, _ = stats(tk["kernel"])
    kernel = np.asarray(tk["kernel"])
    print(f"  {kind} ({len(tk['kernel'])} frames)             p50      p99      max       p1   p50/p99 ÷ kernel   "
          "(+ per-frame excess over the kernel, p50)")
    labels = {"kernel": "kernel (baseline)", "plain": "kernel, plain G-N", "more": "kernel, +1 iteration",
              "exact": "kernel, exact matrix",
              "array": "array path (core)",
              "mapping": "mapping API", "adapter": "by-name adapter", "reference": "previous solve+guard",
              "forward": "one predictor pass"}
    for name in (n for n in PATHS if tk[n]):
        a50, a99, amax, a1 = stats(tk[name])
        goal = ""
        if name in ("array", "mapping", "adapter"):
            excess = float(np.median(np.asarray(tk[name]) - kernel)) * 1e6
            goal = f"  (+{excess:5.1f})   p99 goal {GOAL_US:.0f} µs {'met' if a99 <= GOAL_US else 'NOT met'}"
        print(f"    {labels[name]:22s} {a50:7.1f}  {a99:7.1f}  {amax:7.1f}  {a1:7.1f}   "
              f"{a50 / k50:4.2f} / {a99 / k99:4.2f}{goal}")


def profile(paths: Paths, fr: list[tuple[str, np.ndarray]]) -> None:
    """cProfile of the array path and of the mapping API over the frames: the top entries by own time."""
    for label, fn in (("array path", lambda v: paths.array.solve_array(v, paths.q)),
                      ("mapping API", lambda v: paths.mapping.solve(
                          {ch: float(x) for ch, x in zip(paths.channels, v.tolist(), strict=True) if x == x}, {}))):
        prof = cProfile.Profile()
        run: Callable[[np.ndarray], object] = fn
        prof.enable()
        for _, v in fr:
            run(v)
        prof.disable()
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(8)
        lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
        start = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("ncalls"))
        print(f"  cProfile, {label} ({len(fr)} frames; the profiler's own cost inflates small calls):")
        for ln in lines[start:start + 9]:
            print(f"    {ln}")


def report_guard(path: Path) -> None:
    """The agreements stored in the guard's report."""
    if not path.is_file():
        print(f"  no guard report at {path} (likeness offline guard evaluate ... --out {path})")
        return
    r = json.loads(path.read_text())
    print(f"  guard report ({path.name}, {r['poses']} FEM poses): guard vs FEM {r['guard_vs_fem']:.4f}, "
          f"reduced vs full {r['reduced_vs_full']:.4f}, reduced vs FEM {r['reduced_vs_fem']:.4f}")
    for root, d in r.get("per_dataset", {}).items():
        print(f"    {root}: {d['poses']} poses, guard vs FEM {d['guard_vs_fem']:.4f}, reduced vs full "
              f"{d['reduced_vs_full']:.4f}, FEM passes {d['fem_ok_fraction']:.2f}")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; with ``--record PATH`` the report is also written there (atomically), headed by the
    command, the commit and the hashes of the head config and its predictor."""
    from benchmarks._record import captured, write_report

    args_list = sys.argv[1:] if argv is None else list(argv)
    with captured() as out:
        args = _run(args_list)
    if args.record is not None:
        import hashlib
        import subprocess

        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=ROOT).stdout.strip() or "unknown"
        head = load_head(Path(args.config))
        digests = "; ".join(f"{p.name} sha256 {hashlib.sha256(p.read_bytes()).hexdigest()[:16]}"
                            for p in (Path(args.config), head.path("predictor")) if p is not None)
        write_report(args.record, f"# python benchmarks/skin_solve.py {' '.join(args_list)}\n# commit {commit}; "
                     f"{digests}; {os.cpu_count()} CPUs\n", out.getvalue())
    return 0


def _run(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--random", type=int, default=1000, help="random frames after the performance (default 1000)")
    ap.add_argument("--profile", action="store_true", help="add a cProfile look at the array path and mapping API")
    ap.add_argument("--report", default=str(REPORT), help="guard agreement report to print")
    ap.add_argument("--config", default=str(HEAD),
                    help="head config whose predictor is timed (default: the sample head; e.g. a copy of its folder "
                    "with a candidate predictor, before it is shipped)")
    ap.add_argument("--record", type=Path, default=None, help="also write the report to this file")
    args = ap.parse_args(argv)
    paths = Paths(load_head(Path(args.config)))
    fr = frames(paths.channels, args.random)
    times = {k: {name: [] for name in PATHS} for k in ("performance", "random")}
    for kind, values in fr:
        paths.run(values, times[kind], kind)
    guard, solver = paths.guard, paths.array
    load = os.getloadavg()
    print(f"skin ARKit frame solve, {args.config} (H = {paths.array.predictor.weights.hidden} per axis, output "
          f"rank {paths.array.inverse.rank}, Gauss-Newton matrix rank {paths.array.inverse.matrix_rank}, "
          f"{len(paths.channels)} units, {solver.max_iterations} "
          f"iterations/frame, reduced guard: {guard.calibration.patches} patches, {guard.calibration.vertices} "
          f"vertices; {sum(a.nbytes for a in paths.kernel_args) / 1024:.0f} KB of packed constants); µs; load "
          f"average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} CPUs")
    print("  timings need a quiet machine (load average well under the CPU count); on a loaded one compare the "
          "ratios to the kernel, measured in the same run, and p1")
    for kind, tk in times.items():
        report_times(kind, tk)
    print(f"  array path vs mapping API: {paths.mismatch} of {len(fr)} frames differ; largest pose difference from "
          f"the reference solve {np.degrees(paths.dev):.4f}° (early stop at {solver.xtol:g} of the range); "
          f"unguarded reference solutions passed by the previous guard {paths.ref_ok} of {len(fr)}")
    print("  kept Gauss-Newton matrix vs plain, same frame from the same start: largest pose difference "
          + ", ".join(f"{np.degrees(v):.4f}° ({k})" for k, v in paths.kept_vs_plain.items()))
    print("    surface error on that frame, kept / plain (equal errors: the poses differ along a flat direction): "
          + ", ".join(f"{a:.4g} / {b:.4g} ({k})" for k, (a, b) in paths.kept_vs_plain_error.items()))
    if paths.truncated:
        inv = paths.array.inverse
        print(f"  Gauss-Newton matrix of rank {inv.matrix_rank} vs the exact one (rank {inv.rank}), same frame from "
              "the same start, RMS surface error vs the target:")
        for kind, rows in paths.matrix_vs_exact.items():
            a = np.asarray(rows)
            worse = a[:, 0] - a[:, 1]
            print(f"    {kind}: mean {a[:, 0].mean() * 1e6:.2f} / {a[:, 1].mean() * 1e6:.2f} µm; worse by more than "
                  f"1 µm on {int((worse > 1e-6).sum())} of {len(a)} frames (at most {worse.max() * 1e6:.1f} µm), "
                  f"better by more than 1 µm on {int((worse < -1e-6).sum())}; largest pose difference "
                  f"{np.degrees(a[:, 2].max()):.4f}°")
    n_it = solver.max_iterations
    print(f"  {n_it} iterations per frame vs {n_it + 1}, same frame from the same start, RMS surface error vs the "
          f"target; and the same target held for a second frame of {n_it}:")
    for kind, rows in paths.iterations_vs_more.items():
        a = np.asarray(rows)
        worse, held = a[:, 0] - a[:, 1], a[:, 2] - a[:, 1]
        print(f"    {kind}: mean {a[:, 0].mean() * 1e6:.2f} / {a[:, 1].mean() * 1e6:.2f} µm; worse by more than 1 µm "
              f"on {int((worse > 1e-6).sum())} of {len(a)} frames (at most {worse.max() * 1e6:.1f} µm); held a "
              f"frame: worse than {n_it + 1} by more than 1 µm on {int((held > 1e-6).sum())} (at most "
              f"{held.max() * 1e6:.1f} µm)")
    if args.profile:
        profile(paths, fr)
    report_guard(Path(args.report))
    return args


if __name__ == "__main__":
    sys.exit(main())
