"""What the offline commands share (standard library at module level): the material commands' specimen and mesh
options, and the mold report's printout."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from offline.material.specimen import SpecimenPlan
    from offline.material.virtual_test import MeshSettings

MATERIAL_MODELS = ("neo_hookean", "mooney_rivlin", "yeoh")  # models.material.MATERIAL_MODELS (kept import-free here)


def model_arg(text: str) -> str:
    """A model name in the shared vocabulary; older spellings (neohookean, mooney-rivlin) are accepted."""
    from models.material import canonical_material_model

    try:
        return canonical_material_model(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see :mod:`models.atomic`)."""
    from models.atomic import write_text

    write_text(path, text)


def parse_range(text: str, option: str) -> tuple[float, float]:
    """``LO:HI`` with LO <= HI (UsageError naming ``option`` otherwise)."""
    from models.errors import UsageError

    try:
        lo_s, hi_s = text.split(":")
        lo, hi = float(lo_s), float(hi_s)
    except ValueError:
        raise UsageError(f"{option}: expected LO:HI, got {text!r}") from None
    if not lo <= hi:
        raise UsageError(f"{option}: LO must not exceed HI, got {text!r}")
    return lo, hi


def add_specimen_args(p: argparse.ArgumentParser, default: str) -> None:
    """--specimen, --strip-size, --cylinder-size and --grips."""
    p.add_argument("--specimen", choices=("strip", "cylinder", "auto"), default=default,
                   help="strip for tension, cylinder for compression, auto: strip for ε >= 0 and cylinder for ε < 0 "
                   f"(default {default})")
    p.add_argument("--strip-size", default="55x5x2", metavar="LxWxT",
                   help="strip length x width x thickness in mm (default 55x5x2)")
    p.add_argument("--cylinder-size", default="50x12", metavar="DxH",
                   help="cylinder diameter x height in mm (default 50x12)")
    p.add_argument("--grips", choices=("frictionless", "clamped"), default="frictionless",
                   help="frictionless: ends contract freely (default); clamped: ends fully fixed")


def specimen_plan(args: argparse.Namespace) -> SpecimenPlan:
    """The specimens of --specimen, --strip-size and --cylinder-size."""
    from models.errors import UsageError
    from offline.material.specimen import cylinder, make_plan, parse_dims_mm, strip

    try:
        L, W, T = parse_dims_mm(args.strip_size, 3, "--strip-size")
        D, H = parse_dims_mm(args.cylinder_size, 2, "--cylinder-size")
        return make_plan(args.specimen, strip(L, W, T), cylinder(D, H))
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def mesh_settings(args: argparse.Namespace) -> MeshSettings:
    """The specimen mesh of --order and --refine (the order's default depends on --grips)."""
    from models.errors import UsageError
    from offline.material.virtual_test import MeshSettings, default_mesh_settings

    base = default_mesh_settings(args.grips)
    try:
        return MeshSettings(args.order if args.order else base.order, args.refine)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def print_mold(report: dict[str, Any], out: str | Path) -> int:
    """Print a mold export's checks, channels and volume balance; 0 when every part passed, else 1."""
    ok = True
    for name, c in report["checks"].items():
        ok &= c["ok"]
        print(f"{name}.stl: {'ok' if c['ok'] else 'FAILED'} (watertight {c['watertight']}, oriented "
              f"{c['consistently_oriented']}, self-intersections {c['self_intersections']}, "
              f"{c['volume'] / 1e3:.2f} cm³, {c['components']} component(s))")
    for c in report.get("channels", []):
        x, y, z = c["at_mm"]
        print(f"{c['kind']} hole {c['diameter_mm']:g} mm at ({x:.1f}, {y:.1f}, {z:.1f}) mm (casting frame)")
    vb = report["volume_balance_from_files"]
    print(f"shell cavity − core − channels − pin clearance − flash = {vb['skin_from_mold_mm3'] / 1e3:.3f} cm³ vs skin "
          f"{vb['skin_mm3'] / 1e3:.3f} cm³ (relative difference {vb['relative_difference']:.1e}) -> "
          f"{Path(out) / 'mold_report.json'}")
    return 0 if ok else 1


def add_skin_problem_arguments(p: argparse.ArgumentParser) -> None:
    """The head and the skin problem its poses are solved with: config, mesh, link map, the analytic sheet, the
    element order and the sparse backend (``offline.dataset.build.DatasetSettings``)."""
    p.add_argument("--config", required=True, help="head spec TOML (e.g. heads/sample/head.toml)")
    p.add_argument("--mesh", help="skin mesh folder (e.g. heads/sample/skin)")
    p.add_argument("--linkmap", help="link map file m(p) (default: the head's paths.linkmap)")
    p.add_argument("--synthetic", action="store_true",
                   help="use the analytic test sheet instead of the FEM (pipeline smoke tests and benchmarks)")
    p.add_argument("--element-order", type=int, choices=(1, 2), default=1,
                   help="1: the mesh's linear tets; 2: the same tets quadratic (mid-edge nodes; about 5x the time "
                   "per Newton iteration, far less discretization error in a thin skin)")
    p.add_argument("--backend", default="auto", help="sparse solver backend for the FEM (auto|cholmod|pardiso|superlu)")


def dataset_folder(path: Path, tmp: Path) -> Path:
    """``path`` itself when it is a dataset folder; a pack file is unpacked (hash-checked) under ``tmp``."""
    if not path.is_file():
        return path
    from offline.dataset.pack import unpack_dataset

    unpack_dataset(path, tmp / "dataset")
    return tmp / "dataset"


def joined_folder(paths: list[Path], tmp: Path) -> Path:
    """The one dataset folder that ``paths`` name: itself (unpacked if a pack), or the join of several under ``tmp``."""
    if len(paths) == 1:
        return dataset_folder(paths[0], tmp)
    from offline.dataset.merge import merge_datasets

    folders = [dataset_folder(p, tmp / str(i)) for i, p in enumerate(paths)]
    return merge_datasets(folders, tmp / "joined", names=[str(p) for p in paths]).root
