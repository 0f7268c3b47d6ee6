"""``likeness offline optimize-thickness``: skin thickness optimization.

``--ground-truth-test`` runs the validation: a block with a random MLS thickness field (picked by ``--seed``, as are
the imposed end-face motions) is simulated to make target surfaces, then the field is recovered from the uniform
block. Writes ``DIR/report.json`` (``height_rel_error_max``, ``surface_error_max_m``, settings, input hash, the
objective per iteration) and before/after pictures (``thickness.png``, ``surface_error.png``, ``poses.png``).
"""

from __future__ import annotations

import argparse

METHODS = ("gauss-newton", "lbfgs", "joint")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The test, its seed and size, the method and the output folder."""
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--ground-truth-test", action="store_true",
                   help="recover a random thickness field of a block from its simulated surfaces")
    p.add_argument("--seed", type=int, default=0, help="picks the random thickness field and the motions")
    p.add_argument("--out", required=True, help="output directory (report.json and PNG pictures)")
    p.add_argument("--quick", action="store_true", help="test-size block (seconds instead of a minute)")
    p.add_argument("--method", choices=METHODS, default="gauss-newton",
                   help="gauss-newton / lbfgs: adjoint formulation (exact equilibrium per pose) with that step; "
                        "joint: Gauss-Newton on states and heights together")
    p.add_argument("--max-iterations", type=int, default=40)
    p.add_argument("--threads", type=int, default=1, help="numba kernel threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    """Run the requested optimization and write its report."""
    from dataclasses import replace
    from pathlib import Path

    from models.errors import UsageError
    from offline.design.ground_truth import BlockSettings, run_ground_truth, write_outputs
    from offline.fem import kernel_threads

    if not args.ground_truth_test:
        raise UsageError("optimize-thickness: only --ground-truth-test is available so far (thickness optimization "
                       "of a head's skin is not built yet)")
    if args.max_iterations < 1:
        raise UsageError(f"--max-iterations {args.max_iterations}: must be >= 1")
    if args.threads < 1:
        raise UsageError(f"--threads {args.threads}: must be >= 1")
    settings = BlockSettings.quick() if args.quick else BlockSettings.default()
    settings = replace(settings, method=args.method, max_iterations=args.max_iterations)
    with kernel_threads(args.threads):
        report = run_ground_truth(settings, seed=args.seed, verbose=not args.quiet)
    public = write_outputs(report, Path(args.out))
    print(f"height_rel_error_max={public['height_rel_error_max']:.3e}  "
          f"surface_error_max_m={public['surface_error_max_m']:.3e}  "
          f"(before: {public['surface_error_before_max_m']:.3e} m)  iterations={public['iterations']}  "
          f"time={public['optimize_seconds']:.1f} s  -> {Path(args.out) / 'report.json'}")
    ok = public["height_rel_error_max"] <= 0.01 and public["surface_error_max_m"] <= 1e-5
    print("goal (heights within 1 %, surfaces within 0.01 mm):", "met" if ok else "NOT met")
    return 0 if ok else 1
