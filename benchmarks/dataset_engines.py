"""Pose dataset throughput: poses per hour on the crash-tolerant local pool vs a local Dask cluster (same run).

Both engines solve the same sampled poses of the FEM skin-slab problem (``offline.dataset.box``: a tet slab whose
underside patches are lifted by two actuators through a link map) with the same number of worker processes, each
writing its own pose file; a serial in-process run gives the single-worker baseline. Start-up (pool spawn or
cluster start, worker imports and problem set-up, measured with a few warm-up poses) is timed separately from the
per-pose throughput.

Run: ``python benchmarks/dataset_engines.py [--poses 40] [--workers 2] [--divisions 16 8 3]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    from models.headspec import load_head
    from offline.dataset.box import write_box_problem
    from offline.dataset.generate import generate_dataset
    from offline.dataset.sampling import sample_poses
    from offline.engine import DaskEngine, LocalPoolEngine, SerialEngine

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--divisions", type=int, nargs=3, default=[16, 8, 3])
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        spec = write_box_problem(tmp_path / "problem", divisions=tuple(args.divisions))
        head = load_head(spec.config)
        prob = spec.build()
        print(f"FEM slab: {prob.mesh.n_tets} tets, {prob.mesh.n_nodes} nodes, {len(prob.outer)} surface vertices; "
              f"{args.poses} poses, {args.workers} workers")
        samples = sample_poses(head, args.poses, seed=0)
        lo = np.array([a.min for a in head.actuators])
        hi = np.array([a.max for a in head.actuators])
        common = dict(head=head.name, names=head.actuator_names, units=["m", "m"], lo=lo, hi=hi, seed=0,
                      sampling={}, progress_stream=None)
        generate_dataset(tmp_path / "warmup", spec, samples[:2], engine=SerialEngine(), **common)  # numba caches
        results = {}
        for name, factory in (("serial (1 process)", SerialEngine),
                              ("local pool", lambda: LocalPoolEngine(args.workers)),
                              ("dask-local", lambda: DaskEngine(None, n_workers=args.workers))):
            t0 = time.perf_counter()
            engine = factory()
            with engine:
                # Start-up: workers spawn, import and build the problem (a few warm-up poses, not counted below).
                generate_dataset(tmp_path / ("warm-" + name.split()[0]), spec, samples[-2 * args.workers:],
                                 engine=engine, **common)
                t_start = time.perf_counter() - t0
                summary = generate_dataset(tmp_path / name.split()[0], spec, samples, engine=engine, **common)
            assert summary["complete"], summary
            results[name] = summary["poses_per_hour"]
            print(f"{name:>20}: start-up {t_start:6.2f} s, {summary['seconds']:6.1f} s for {args.poses} poses → "
                  f"{summary['poses_per_hour']:8.0f} poses/h ({summary['not_converged']} not converged)")
        base = results["serial (1 process)"]
        print(f"\nlocal pool / serial: {results['local pool'] / base:.2f}×   dask-local / serial: "
              f"{results['dask-local'] / base:.2f}×   dask-local / local pool: "
              f"{results['dask-local'] / results['local pool']:.2f}×")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
