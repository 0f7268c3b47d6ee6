"""Skin predictor latency (onnxruntime, one thread) vs a memory-bandwidth floor and the paper; inverse-solve time.

For 5k, 50k and 100k surface vertices, a KSNN (13 actuators → 26 tanh → 3·V, three heads in one ONNX graph) is
timed for one pose (and, as the baseline, run the way the predictor used to run it: plain ``session.run``, weight
prepacking on), per pose in a batch of 64, and as the int8 (MatMulNBits) variant for one pose, with its RMS
difference to float32. The floor is the time to stream the
output-layer weight bytes (W2 and b2, float32) once: the faster of two read-only reductions (a max and a BLAS
matrix-vector product with ones) over an array of that size. Every timed call runs in turn with the others, round
after round, so a busy machine slows them alike, and is timed in the thread's CPU time (on an oversubscribed machine
wall time mostly measures the scheduler); figures are medians. The predictor is timed writing into a preallocated
output (``out=``, as a control loop calls it) and returning a new array. Then the hidden-space inverse solve
(52 face units) is timed per frame, alone and with the strain guard.

Run: ``python benchmarks/predictor_latency.py [--sizes 5000 50000 100000] [--repeats 200]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.ksnn_solve import KsnnInverse  # noqa: E402
from models.predictor import INPUT_NAME, KsnnWeights, SkinPredictor  # noqa: E402
from offline.train.export import export_int8, export_predictor, predictor_metadata  # noqa: E402

PAPER_MS = (1.4, 1.6)
A, H = 13, 26


def timeit(fn, repeats: int, warmup: int = 10) -> float:
    """Median wall time of ``fn()`` in seconds."""
    for _ in range(warmup):
        fn()
    ts = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts[i] = time.perf_counter() - t0
    return float(np.median(ts))


def interleaved(fns: dict[str, Callable[[], object]], repeats: int, warmup: int = 5) -> dict[str, float]:
    """Median thread CPU time in seconds of each function, calling them in turn, one call each per round."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    ts = np.empty((repeats, len(fns)))
    for i in range(repeats):
        for j, fn in enumerate(fns.values()):
            t0 = time.thread_time()
            fn()
            ts[i, j] = time.thread_time() - t0
    return {name: float(np.median(ts[:, j])) for j, name in enumerate(fns)}


def make_model(folder: Path, n_vertices: int, n_units: int = 0, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    lo, hi = -np.ones(A) * 0.4, np.ones(A) * 0.6
    w = KsnnWeights(lo, hi, rng.normal(size=(3, A, H)), rng.normal(size=(3, H)) * 0.3,
                    rng.normal(size=(3, H, n_vertices)) * 1e-4, rng.normal(size=(3, n_vertices)) * 1e-5)
    side = int(np.ceil(np.sqrt(n_vertices)))
    u, v = np.divmod(np.arange(n_vertices), side)
    base = np.stack([u * 1e-3, v * 1e-3, np.zeros(n_vertices)], 1)
    idx = np.arange(n_vertices)
    ok = (v < side - 1) & (idx + side + 1 < n_vertices)
    a = idx[ok]
    faces = np.concatenate([np.stack([a, a + side, a + side + 1], 1), np.stack([a, a + side + 1, a + 1], 1)])
    fu = None
    names: list[str] = []
    if n_units:
        P = rng.uniform(lo, hi, size=(n_units, A))
        fu = np.stack([w.offsets(p) - w.offsets((lo + hi) / 2) for p in P])
        names = [f"unit{i}" for i in range(n_units)]
    meta = predictor_metadata(head="bench", names=[f"a{i}" for i in range(A)], units=["rad"] * A, weights=w,
                              base_vertices=base, faces=faces, face_unit_names=names, face_unit_offsets=fu)
    path = folder / f"ksnn_{n_vertices}.onnx"
    export_predictor(path, w, meta)
    return path


def floor_functions(n_vertices: int) -> dict[str, Callable[[], object]]:
    """Read-only passes over an array the size of the output-layer weights (W2 and b2, float32)."""
    W = np.random.default_rng(1).normal(size=(3 * (H + 1), n_vertices)).astype(np.float32)
    flat = W.reshape(-1)
    ones = np.ones(W.shape[0], dtype=np.float32)
    acc = np.empty(n_vertices, dtype=np.float32)
    return {"floor max": lambda: np.maximum.reduce(flat), "floor gemv": lambda: np.dot(ones, W, out=acc)}


def previous_predictor(path: Path) -> Callable[[np.ndarray], np.ndarray]:
    """The file run as the predictor used to: default session options (weights prepacked), plain ``run``."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    return lambda p: session.run(None, {INPUT_NAME: p.astype(np.float32)[None]})[0][0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[5_000, 50_000, 100_000])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args(argv)
    logging.getLogger("onnxruntime.quantization").setLevel(logging.WARNING)  # the int8 export logs every node
    print(f"KSNN {A} → {H} tanh → 3·V, onnxruntime 1 thread; paper: {PAPER_MS[0]}–{PAPER_MS[1]} ms per pose; "
          f"medians of interleaved calls, thread CPU µs; load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs")
    print(f"{'vertices':>9} {'floor':>6} {'fp32':>6} {'/floor':>6} {'new arr':>7} {'/floor':>6} "
          f"{'before':>6} {'/floor':>6} {'batch/pose':>10} {'int8':>6} {'int8/fp32':>9} "
          f"{'int8 RMS mm':>11} {'paper/fp32':>10}")
    rng = np.random.default_rng(2)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            path = make_model(Path(tmp), n)
            sp = SkinPredictor(path, threads=1)
            before = previous_predictor(path)
            q = SkinPredictor(export_int8(path, Path(tmp) / f"ksnn_{n}_int8.onnx"), threads=1)
            p = rng.uniform(sp.lo, sp.hi)
            P = rng.uniform(sp.lo, sp.hi, size=(args.batch, A)).astype(np.float32)
            reps = max(20, args.repeats * 5000 // n)
            out = np.empty((n, 3), dtype=np.float32)
            fns = floor_functions(n)
            fns |= {"fp32": lambda sp=sp, p=p, o=out: sp.predict_offsets(p, out=o),
                    "new": lambda sp=sp, p=p: sp.predict_offsets(p),
                    "before": lambda before=before, p=p: before(p),
                    "int8": lambda q=q, p=p, o=out: q.predict_offsets(p, out=o)}
            t = interleaved(fns, reps)
            floor = min(t["floor max"], t["floor gemv"])
            t0 = time.thread_time()
            n_batches = max(3, reps // args.batch)
            for _ in range(n_batches):
                sp.predict_offsets(P)
            t_batch = (time.thread_time() - t0) / n_batches / args.batch
            Q = rng.uniform(sp.lo, sp.hi, size=(64, A))
            rms_mm = float(np.sqrt(np.mean((q.predict_offsets(Q) - sp.predict_offsets(Q)) ** 2))) * 1e3
            vs_paper = f"{PAPER_MS[0] * 1e-3 / t['fp32']:.1f}–{PAPER_MS[1] * 1e-3 / t['fp32']:.1f}"
            print(f"{n:>9} {floor * 1e6:>6.0f} {t['fp32'] * 1e6:>6.0f} {t['fp32'] / floor:>6.2f} "
                  f"{t['new'] * 1e6:>7.0f} {t['new'] / floor:>6.2f} "
                  f"{t['before'] * 1e6:>6.0f} {t['before'] / floor:>6.2f} {t_batch * 1e6:>10.1f} "
                  f"{t['int8'] * 1e6:>6.0f} {t['int8'] / t['fp32']:>9.2f} {rms_mm:>11.4f} {vs_paper:>10}")
        print("floor: streaming the output-layer weights once (fastest read-only pass); fp32: into a "
              "preallocated output; new arr: returning a new array; before: the same file run the previous way "
              "(prepacked weights, plain run); int8: "
              f"MatMulNBits into a preallocated output. Load average now {os.getloadavg()[0]:.1f}.")
        # Inverse solve per frame (52 face units, 5k vertices): warm-started along a slowly moving expression.
        n = args.sizes[0]
        sp = SkinPredictor(make_model(Path(tmp), n, n_units=52, seed=3), threads=1)
        inv = KsnnInverse(sp.weights, sp.face_unit_offsets)
        t_pre = timeit(lambda: KsnnInverse(sp.weights, sp.face_unit_offsets), 3, warmup=1)
        frames = 400
        W = np.clip(0.5 + 0.4 * np.sin(np.linspace(0, 6, frames)[:, None] + rng.uniform(0, 6, 52)[None]), 0, 1) / 52
        p = (sp.lo + sp.hi) / 2
        times, iters, resid = [], [], []
        for w in W:
            t0 = time.perf_counter()
            res = inv.solve(w, p_prev=p, max_iterations=8)
            times.append(time.perf_counter() - t0)
            iters.append(res.iterations)
            resid.append(res.residual_rms)
            p = res.p
        guard = timeit(lambda: sp.strain_extremes(sp.predict(p)), 100)
        t_solve = float(np.median(times))
        print(f"\ninverse solve, {n} vertices, 52 face units: precompute {t_pre * 1e3:.1f} ms once; per frame median "
              f"{t_solve * 1e6:.0f} µs (p95 {np.percentile(times, 95) * 1e6:.0f} µs), {np.mean(iters):.1f} "
              f"iterations, residual {np.median(resid) * 1e6:.1f} µm (random targets, not all reachable); "
              f"strain guard (predict + stretch) "
              f"{guard * 1e6:.0f} µs")
        t_vertex_space = timeit(lambda: sp.jacobian(p), 20)
        print(f"one vertex-space Jacobian (V·3 × A) alone takes {t_vertex_space * 1e6:.0f} µs: the hidden-space "
              f"step is {t_vertex_space / (t_solve / max(np.mean(iters), 1)):.1f}× cheaper per iteration")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
