"""``likeness offline uniaxial``: a virtual uniaxial tension/compression test of a hyperelastic material (FEM, or
the homogeneous closed form), written as a strain,force_N CSV."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from offline.cli._common import (
    MATERIAL_MODELS,
    add_specimen_args,
    mesh_settings,
    model_arg,
    specimen_plan,
    write_text_atomic,
)

if TYPE_CHECKING:
    from offline.material.models import MaterialParams


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The material, the strains, the specimen and the solver."""
    p.description = ("Stretch or compress a virtual specimen with the FEM and write nominal strain versus axial "
                     "force. Tension uses the 55x5x2 mm strip, compression the 50x12 mm cylinder (--specimen auto).")
    p.add_argument("--material", type=model_arg, choices=MATERIAL_MODELS, default="neo_hookean",
                   help="hyperelastic model")
    p.add_argument("--E", type=float, default=78_000.0, help="small-strain Young's modulus, Pa (default 78000)")
    p.add_argument("--nu", type=float, default=0.47, help="small-strain Poisson's ratio (default 0.47)")
    p.add_argument("--c01", type=float, default=None, help="Mooney-Rivlin c01, Pa (c10 = mu/2 - c01)")
    p.add_argument("--c20", type=float, default=None, help="Yeoh c20, Pa (c10 = mu/2)")
    p.add_argument("--c30", type=float, default=None, help="Yeoh c30, Pa")
    p.add_argument("--strain", default="-0.2:0.5:15", help="START:STOP:COUNT or comma list of nominal strains")
    add_specimen_args(p, "auto")
    p.add_argument("--solver", choices=("fem", "closed-form"), default="fem",
                   help="fem (default) or the homogeneous closed form (frictionless grips only)")
    p.add_argument("--order", type=int, choices=(1, 2), default=None,
                   help="tet order (default: 1 for frictionless grips, whose answer is homogeneous; 2 for clamped)")
    p.add_argument("--refine", type=int, default=1, help="mesh density multiplier (default 1)")
    p.add_argument("--out", required=True, type=Path, help="output CSV (header strain,force_N)")


def run(args: argparse.Namespace) -> int:
    """Run the test and write the CSV."""
    import numpy as np

    from models.errors import UsageError
    from offline.material.fit import closed_form_forces
    from offline.material.virtual_test import VirtualTestError, run_plan

    params = material_params(args)
    strains = np.array(parse_strains(args.strain))
    plan = specimen_plan(args)
    if args.solver == "closed-form":
        if args.grips != "frictionless":
            raise UsageError("--solver closed-form is exact only for --grips frictionless")
        forces = closed_form_forces(params, strains, plan)
    else:
        try:
            forces = run_plan(params, plan, strains, grips=args.grips, mesh_settings=mesh_settings(args))
        except VirtualTestError as exc:
            raise UsageError(str(exc)) from None
    lines = ["strain,force_N"] + [f"{e + 0.0:.12g},{f + 0.0:.12g}" for e, f in zip(strains, forces, strict=True)]
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print(f"wrote {args.out} ({strains.size} strains, {params.model} E={params.E:g} Pa nu={params.nu:g}, "
          f"{args.grips} grips, {args.solver})")
    return 0


def parse_strains(text: str) -> list[float]:
    """``start:stop:count`` (inclusive, evenly spaced) or a comma-separated list of nominal strains."""
    from models.errors import UsageError

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
        raise UsageError(f"--strain: expected START:STOP:COUNT (e.g. -0.2:0.5:15) or a comma list, got {text!r}") \
            from None
    if not values:
        raise UsageError("--strain: no strains given")
    for v in values:
        if not (v == v and -0.9 < v <= 5.0):
            raise UsageError(f"--strain: nominal strains must be fractions in (-0.9, 5], got {v!r} (percent given?)")
    return values


def material_params(args: argparse.Namespace) -> MaterialParams:
    """The material of --material, --E, --nu and the model's shape parameters."""
    from models.errors import UsageError
    from offline.material.models import MaterialParams

    extra = {}
    allowed = {"neo_hookean": (), "mooney_rivlin": ("c01",), "yeoh": ("c20", "c30")}[args.material]
    for name in ("c01", "c20", "c30"):
        value = getattr(args, name)
        if value is None:
            continue
        if name not in allowed:
            raise UsageError(f"--{name} does not apply to --material {args.material}")
        extra[name] = value
    try:
        return MaterialParams(args.material, args.E, args.nu, extra)
    except ValueError as exc:
        raise UsageError(f"material: {exc}") from None
