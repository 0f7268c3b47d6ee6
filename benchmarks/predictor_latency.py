"""Skin predictor latency (onnxruntime, one thread) vs the paper and vs a memory-bandwidth floor; inverse-solve time.

For 5k, 50k and 100k surface vertices, a KSNN (13 actuators → 26 tanh → 3·V, three heads in one ONNX graph) is
timed for one pose, per pose in a batch of 64, and as the int8 (MatMulNBits) variant for one pose, against the
paper's 1.4–1.6 ms per pose and against the time NumPy needs to stream the same bytes (the output-layer weights
read once plus the output written once) in this run. Then the hidden-space inverse solve (52 face units) is timed
per frame, alone and with the strain guard.

Run: ``python benchmarks/predictor_latency.py [--sizes 5000 50000 100000] [--repeats 200]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.ksnn_solve import KsnnInverse  # noqa: E402
from models.predictor import KsnnWeights, SkinPredictor  # noqa: E402
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


def bandwidth_floor(n_vertices: int, repeats: int) -> tuple[float, float]:
    """Seconds to read the output-layer weights once and write the output once (NumPy copy), and NumPy h @ W2."""
    W2 = np.random.default_rng(1).normal(size=(H, 3 * n_vertices)).astype(np.float32)
    dst = np.empty_like(W2)
    out = np.empty(3 * n_vertices, dtype=np.float32)
    h = np.ones(H, dtype=np.float32)

    def copy() -> None:
        np.copyto(dst, W2)

    def dot() -> None:
        np.dot(h, W2, out=out)

    # A copy reads and writes W2's bytes; the predictor reads them once and writes 3V floats: scale to that.
    t_copy = timeit(copy, repeats)
    bytes_copy = 2 * W2.nbytes
    bytes_needed = W2.nbytes + out.nbytes
    return t_copy * bytes_needed / bytes_copy, timeit(dot, repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[5_000, 50_000, 100_000])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args(argv)
    print(f"KSNN {A} → {H} tanh → 3·V, onnxruntime 1 thread; paper: {PAPER_MS[0]}–{PAPER_MS[1]} ms per pose")
    print(f"{'vertices':>9} {'single µs':>10} {'batch µs/pose':>14} {'int8 µs':>8} {'floor µs':>9} "
          f"{'numpy h@W2 µs':>14} {'single/floor':>13} {'paper/single':>13}")
    rng = np.random.default_rng(2)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            path = make_model(Path(tmp), n)
            sp = SkinPredictor(path, threads=1)
            q = SkinPredictor(export_int8(path, Path(tmp) / f"ksnn_{n}_int8.onnx"), threads=1)
            p = rng.uniform(sp.lo, sp.hi)
            P = rng.uniform(sp.lo, sp.hi, size=(args.batch, A)).astype(np.float32)
            reps = max(20, args.repeats * 5000 // n)
            t_single = timeit(lambda sp=sp, p=p: sp.predict_offsets(p), reps)
            t_batch = timeit(lambda sp=sp, P=P: sp.predict_offsets(P), max(5, reps // args.batch)) / args.batch
            t_int8 = timeit(lambda q=q, p=p: q.predict_offsets(p), reps)
            floor, t_dot = bandwidth_floor(n, reps)
            vs_paper = f"{PAPER_MS[0] * 1e-3 / t_single:.1f}–{PAPER_MS[1] * 1e-3 / t_single:.1f}"
            print(f"{n:>9} {t_single * 1e6:>10.1f} {t_batch * 1e6:>14.1f} {t_int8 * 1e6:>8.1f} {floor * 1e6:>9.1f} "
                  f"{t_dot * 1e6:>14.1f} "
                  f"{t_single / floor:>13.2f} {vs_paper:>13}")
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
