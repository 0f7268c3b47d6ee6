"""``likeness offline fit-material``: fit hyperelastic parameters to measured force-strain data and report which
parameters the data identify."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from offline.cli._common import (
    MATERIAL_MODELS,
    add_specimen_args,
    mesh_settings,
    model_arg,
    parse_range,
    specimen_plan,
    write_text_atomic,
)

if TYPE_CHECKING:
    import numpy as np

    from offline.material.fit import FitResult
    from offline.material.measurements import Measurement
    from offline.material.models import MaterialParams


def add_arguments(q: argparse.ArgumentParser) -> None:
    """The measurement files, the model, the method, the specimen and the outputs."""
    q.description = ("Fit E and nu (and model shape parameters) to measurements by simulated annealing and/or "
                     "least squares, and report which parameters the data identify (95 % intervals from the residual "
                     "Jacobian; tension-only data do not pin nu). Accepts strain,force_N or displacement_m,force_N "
                     "CSVs and the ';'-separated tensile-test exports in data/tensile/ (specimen from the file "
                     "header); several files are fitted jointly.")
    q.add_argument("measurements", type=Path, nargs="+",
                   help="measurement file(s); several files (e.g. a tension strip and a compression cylinder) are "
                   "fitted jointly, each sample on its own specimen")
    q.add_argument("--model", type=model_arg, choices=MATERIAL_MODELS, default="neo_hookean",
                   help="model to fit (default neo_hookean)")
    q.add_argument("--method", choices=("anneal", "lsq", "both"), default="both",
                   help="simulated annealing, least squares, or both keeping the better (default both)")
    add_specimen_args(q, "auto")
    q.add_argument("--strain-range", default="-0.2:0.5", metavar="LO:HI",
                   help="fit only samples with LO <= strain <= HI (default -0.2:0.5, the skin's working range)")
    q.add_argument("--nu-range", default="0.3:0.499", metavar="LO:HI",
                   help="bounds of Poisson's ratio (default 0.3:0.499; LO=HI fixes it)")
    q.add_argument("--seed", type=int, default=0, help="annealing random seed (default 0)")
    q.add_argument("--anneal-maxiter", type=int, default=300, help="annealing iterations (default 300)")
    q.add_argument("--order", type=int, choices=(1, 2), default=None, help="tet order for clamped-grip FEM")
    q.add_argument("--refine", type=int, default=1, help="mesh density multiplier for clamped-grip FEM")
    q.add_argument("--plot", type=Path, default=None, help="PNG of measured versus simulated curves")
    q.add_argument("--out", type=Path, default=None, help="JSON with the fitted parameters and errors")


def run(args: argparse.Namespace) -> int:
    """Fit, print the parameters and their identifiability, write the JSON and the plot."""
    import json
    import sys

    from models.errors import UsageError
    from offline.material.fit import fit_measurement
    from offline.material.virtual_test import VirtualTestError, run_plan

    lo, hi = parse_range(args.strain_range, "--strain-range")
    nu_bounds = parse_range(args.nu_range, "--nu-range")
    meas, plan, total = _load_measurements(args, lo, hi)
    settings = mesh_settings(args)

    def fem_model(params: MaterialParams, strain: np.ndarray) -> np.ndarray:
        return run_plan(params, plan, strain, grips="clamped", mesh_settings=settings)

    try:
        result = fit_measurement(meas, plan, model=args.model, method=args.method, grips=args.grips,
                                 nu_bounds=nu_bounds, seed=args.seed, anneal_maxiter=args.anneal_maxiter,
                                 fem_model=fem_model if args.grips == "clamped" else None)
    except (ValueError, VirtualTestError) as exc:
        raise UsageError(f"{meas.source}: {exc}") from None
    summary = result.as_dict()
    files = [str(p) for p in args.measurements]
    summary.update({"measurements": " + ".join(files), "measurements_files": files, "file_format": meas.file_format,
                    "samples_used": len(meas), "samples_in_file": total, "specimens": plan.as_dict()})
    _print_fit(result, len(meas))
    if args.out is not None:
        write_text_atomic(args.out, json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.out}")
    if args.plot is not None:
        from offline.material.plot import plot_fit

        names = " + ".join(p.name for p in args.measurements)
        plot_fit(result, plan, args.plot, title=f"{names}: {args.model} fit")
        print(f"wrote {args.plot}")
    sys.stdout.flush()
    return 0


def _load_measurements(args: argparse.Namespace, lo: float, hi: float) -> tuple[Measurement, Any, int]:
    """The measurements of the files within the strain range (jointly when several), their specimen plan and how
    many samples the files held."""
    from models.errors import UsageError
    from offline.material.measurements import MeasurementError, combine_measurements, load_measurements
    from offline.material.specimen import SpecimenPlan

    plan: Any = specimen_plan(args)
    loaded = []
    total = 0
    for path in args.measurements:
        try:
            one = load_measurements(path, plan)
        except MeasurementError as exc:
            raise UsageError(str(exc)) from None
        if one.specimen is not None:
            print(f"{path.name}: specimen from the file header: {one.specimen.describe()}, cross-section "
                  f"{one.specimen.area * 1e4:g} cm² (--specimen ignored)")
        total += len(one)
        one = one.select(lo, hi)
        if len(one) == 0:
            raise UsageError(f"{path}: no samples lie in --strain-range {lo}:{hi}")
        loaded.append(one)
    if len(loaded) == 1:
        meas = loaded[0]
        if meas.specimen is not None:
            plan = SpecimenPlan(meas.specimen, meas.specimen)
    else:
        meas, plan = combine_measurements(loaded, plan)
        print(f"joint fit of {len(loaded)} files: " + "; ".join(f"{k}: {v['kind']}, {v['samples']} samples"
                                                             for k, v in plan.as_dict().items()))
    if len(meas) < 3:
        raise UsageError(f"only {len(meas)} of {total} samples lie in --strain-range {lo}:{hi}")
    return meas, plan, total


def _print_fit(result: FitResult, samples: int) -> None:
    """Each method's parameters, the chosen fit, the forward model and what the data identify."""
    for one in result.runs:
        se = "".join(f", ±{v:.3g} {k}" for k, v in one.stderr.items())
        print(f"{one.method:>6}: E = {one.params.E:.6g} Pa, nu = {one.params.nu:.4f}{se} "
              f"({one.evaluations} evaluations, {one.seconds:.2f} s)")
    print(f"chosen {result.method}: E = {result.params.E:.6g} Pa, nu = {result.params.nu:.4f}; RMS force error "
          f"{result.rms_force_N:.4g} N ({100 * result.relative_rms:.2f} % of max |force|), {samples} samples")
    print(f"forward model: {result.surrogate}")
    for line in result.identifiability.get("summary", []):
        print(f"identifiability: {line}")
