"""``likeness offline uniaxial`` (virtual standard test) and ``likeness offline fit-material`` (parameter fit).

Only the standard library is imported at module level; numpy, SciPy, the FEM and matplotlib load inside the
commands.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from likeness.cli import CliError

_MODELS = ("neo_hookean", "mooney_rivlin", "yeoh")  # models.material.MATERIAL_MODELS (kept import-free here)


def _model_arg(text: str) -> str:
    """A model name in the shared vocabulary; older spellings (neohookean, mooney-rivlin) are accepted."""
    from models.material import canonical_material_model

    try:
        return canonical_material_model(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see :mod:`models.atomic`)."""
    from models.atomic import write_text

    write_text(path, text)


def _parse_strains(text: str) -> list[float]:
    """``start:stop:count`` (inclusive, evenly spaced) or a comma-separated list of nominal strains."""
    try:
        if ":" in text:
            parts = text.split(":")
            if len(parts) != 3:
                raise ValueError
            start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
            if count < 1:
                raise ValueError
            if count == 1:
                values = [start]
            else:
                values = [round(start + (stop - start) * i / (count - 1), 12) for i in range(count)]
        else:
            values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise CliError(f"--strain: expected START:STOP:COUNT (e.g. -0.2:0.5:15) or a comma list, got {text!r}") \
            from None
    if not values:
        raise CliError("--strain: no strains given")
    for v in values:
        if not (v == v and -0.9 < v <= 5.0):
            raise CliError(f"--strain: nominal strains must be fractions in (-0.9, 5], got {v!r} (percent given?)")
    return values


def _parse_range(text: str, option: str) -> tuple[float, float]:
    try:
        lo_s, hi_s = text.split(":")
        lo, hi = float(lo_s), float(hi_s)
    except ValueError:
        raise CliError(f"{option}: expected LO:HI, got {text!r}") from None
    if not lo <= hi:
        raise CliError(f"{option}: LO must not exceed HI, got {text!r}")
    return lo, hi


def _add_specimen_args(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--specimen", choices=("strip", "cylinder", "auto"), default=default,
                   help="strip for tension, cylinder for compression, auto: strip for ε >= 0 and cylinder for ε < 0 "
                   f"(default {default})")
    p.add_argument("--strip-size", default="55x5x2", metavar="LxWxT",
                   help="strip length x width x thickness in mm (default 55x5x2)")
    p.add_argument("--cylinder-size", default="50x12", metavar="DxH",
                   help="cylinder diameter x height in mm (default 50x12)")
    p.add_argument("--grips", choices=("frictionless", "clamped"), default="frictionless",
                   help="frictionless: ends contract freely (default); clamped: ends fully fixed")


def _plan(args: argparse.Namespace):
    from offline.material.specimen import cylinder, make_plan, parse_dims_mm, strip

    try:
        L, W, T = parse_dims_mm(args.strip_size, 3, "--strip-size")
        D, H = parse_dims_mm(args.cylinder_size, 2, "--cylinder-size")
        return make_plan(args.specimen, strip(L, W, T), cylinder(D, H))
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _mesh_settings(args: argparse.Namespace):
    from offline.material.virtual_test import MeshSettings, default_mesh_settings

    base = default_mesh_settings(args.grips)
    try:
        return MeshSettings(args.order if args.order else base.order, args.refine)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``uniaxial`` and ``fit-material`` to the ``likeness offline`` group."""
    p = subparsers.add_parser(
        "uniaxial", help="virtual uniaxial tension/compression test (FEM), writes strain,force_N CSV",
        description="Stretch or compress a virtual specimen with the FEM and write nominal strain versus axial "
        "force. Tension uses the 55x5x2 mm strip, compression the 50x12 mm cylinder (--specimen auto).")
    p.add_argument("--material", type=_model_arg, choices=_MODELS, default="neo_hookean",
                   help="hyperelastic model")
    p.add_argument("--E", type=float, default=78_000.0, help="small-strain Young's modulus, Pa (default 78000)")
    p.add_argument("--nu", type=float, default=0.47, help="small-strain Poisson's ratio (default 0.47)")
    p.add_argument("--c01", type=float, default=None, help="Mooney-Rivlin c01, Pa (c10 = mu/2 - c01)")
    p.add_argument("--c20", type=float, default=None, help="Yeoh c20, Pa (c10 = mu/2)")
    p.add_argument("--c30", type=float, default=None, help="Yeoh c30, Pa")
    p.add_argument("--strain", default="-0.2:0.5:15", help="START:STOP:COUNT or comma list of nominal strains")
    _add_specimen_args(p, "auto")
    p.add_argument("--solver", choices=("fem", "closed-form"), default="fem",
                   help="fem (default) or the homogeneous closed form (frictionless grips only)")
    p.add_argument("--order", type=int, choices=(1, 2), default=None,
                   help="tet order (default: 1 for frictionless grips, whose answer is homogeneous; 2 for clamped)")
    p.add_argument("--refine", type=int, default=1, help="mesh density multiplier (default 1)")
    p.add_argument("--out", required=True, type=Path, help="output CSV (header strain,force_N)")
    p.set_defaults(func=_cmd_uniaxial)

    q = subparsers.add_parser(
        "fit-material", help="fit hyperelastic parameters to measured force-strain data",
        description="Fit E and nu (and model shape parameters) to measurements by simulated annealing and/or "
        "least squares, and report which parameters the data identify (95 % intervals from the residual "
        "Jacobian; tension-only data do not pin nu). Accepts strain,force_N or displacement_m,force_N CSVs and "
        "the ';'-separated tensile-test exports in data/tensile/ (specimen from the file header); several "
        "files are fitted jointly.")
    q.add_argument("measurements", type=Path, nargs="+",
                   help="measurement file(s); several files (e.g. a tension strip and a compression cylinder) are "
                   "fitted jointly, each sample on its own specimen")
    q.add_argument("--model", type=_model_arg, choices=_MODELS, default="neo_hookean",
                   help="model to fit (default neo_hookean)")
    q.add_argument("--method", choices=("anneal", "lsq", "both"), default="both",
                   help="simulated annealing, least squares, or both keeping the better (default both)")
    _add_specimen_args(q, "auto")
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
    q.set_defaults(func=_cmd_fit)


def _material(args: argparse.Namespace):
    from offline.material.models import MaterialParams

    extra = {}
    allowed = {"neo_hookean": (), "mooney_rivlin": ("c01",), "yeoh": ("c20", "c30")}[args.material]
    for name in ("c01", "c20", "c30"):
        value = getattr(args, name)
        if value is None:
            continue
        if name not in allowed:
            raise CliError(f"--{name} does not apply to --material {args.material}")
        extra[name] = value
    try:
        return MaterialParams(args.material, args.E, args.nu, extra)
    except ValueError as exc:
        raise CliError(f"material: {exc}") from None


def _cmd_uniaxial(args: argparse.Namespace) -> int:
    import numpy as np

    from offline.material.fit import closed_form_forces
    from offline.material.virtual_test import VirtualTestError, run_plan

    params = _material(args)
    strains = np.array(_parse_strains(args.strain))
    plan = _plan(args)
    if args.solver == "closed-form":
        if args.grips != "frictionless":
            raise CliError("--solver closed-form is exact only for --grips frictionless")
        forces = closed_form_forces(params, strains, plan)
    else:
        try:
            forces = run_plan(params, plan, strains, grips=args.grips, mesh_settings=_mesh_settings(args))
        except VirtualTestError as exc:
            raise CliError(str(exc)) from None
    lines = ["strain,force_N"] + [f"{e + 0.0:.12g},{f + 0.0:.12g}" for e, f in zip(strains, forces, strict=True)]
    _atomic_write_text(args.out, "\n".join(lines) + "\n")
    print(f"wrote {args.out} ({strains.size} strains, {params.model} E={params.E:g} Pa nu={params.nu:g}, "
          f"{args.grips} grips, {args.solver})")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from offline.material.fit import fit_measurement
    from offline.material.measurements import MeasurementError, combine_measurements, load_measurements
    from offline.material.specimen import SpecimenPlan
    from offline.material.virtual_test import VirtualTestError, run_plan

    plan = _plan(args)
    lo, hi = _parse_range(args.strain_range, "--strain-range")
    nu_bounds = _parse_range(args.nu_range, "--nu-range")
    loaded = []
    total = 0
    for path in args.measurements:
        try:
            one = load_measurements(path, plan)
        except MeasurementError as exc:
            raise CliError(str(exc)) from None
        if one.specimen is not None:
            print(f"{path.name}: specimen from the file header: {one.specimen.describe()}, cross-section "
                  f"{one.specimen.area * 1e4:g} cm² (--specimen ignored)")
        total += len(one)
        one = one.select(lo, hi)
        if len(one) == 0:
            raise CliError(f"{path}: no samples lie in --strain-range {lo}:{hi}")
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
        raise CliError(f"only {len(meas)} of {total} samples lie in --strain-range {lo}:{hi}")
    settings = _mesh_settings(args)

    def fem_model(params, strain):
        return run_plan(params, plan, strain, grips="clamped", mesh_settings=settings)

    try:
        result = fit_measurement(meas, plan, model=args.model, method=args.method, grips=args.grips,
                                 nu_bounds=nu_bounds, seed=args.seed, anneal_maxiter=args.anneal_maxiter,
                                 fem_model=fem_model if args.grips == "clamped" else None)
    except (ValueError, VirtualTestError) as exc:
        raise CliError(f"{meas.source}: {exc}") from None
    summary = result.as_dict()
    files = [str(p) for p in args.measurements]
    summary.update({"measurements": " + ".join(files), "measurements_files": files, "file_format": meas.file_format,
                    "samples_used": len(meas), "samples_in_file": total, "specimens": plan.as_dict()})
    for run in result.runs:
        se = "".join(f", ±{v:.3g} {k}" for k, v in run.stderr.items())
        print(f"{run.method:>6}: E = {run.params.E:.6g} Pa, nu = {run.params.nu:.4f}{se} "
              f"({run.evaluations} evaluations, {run.seconds:.2f} s)")
    print(f"chosen {result.method}: E = {result.params.E:.6g} Pa, nu = {result.params.nu:.4f}; RMS force error "
          f"{result.rms_force_N:.4g} N ({100 * result.relative_rms:.2f} % of max |force|), {len(meas)} samples")
    print(f"forward model: {result.surrogate}")
    for line in result.identifiability.get("summary", []):
        print(f"identifiability: {line}")
    if args.out is not None:
        _atomic_write_text(args.out, json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.out}")
    if args.plot is not None:
        from offline.material.plot import plot_fit

        names = " + ".join(p.name for p in args.measurements)
        plot_fit(result, plan, args.plot, title=f"{names}: {args.model} fit")
        print(f"wrote {args.plot}")
    sys.stdout.flush()
    return 0
