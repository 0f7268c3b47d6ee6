"""``likeness offline export-mold``: STL files (mm) of a skin and its two-part casting mold, checked."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The skin folder, the output folder and the mold's dimensions."""
    from offline.design.mold import __doc__ as mold_doc

    p.description = mold_doc
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--skin", required=True, help="skin folder (skin.vtu + face_units.npz), e.g. CLONE_DIR/skin")
    p.add_argument("--out", required=True, help="output folder for the STL files and mold_report.json")
    p.add_argument("--margin-mm", type=float, default=12.0, help="mold wall around the skin (default 12)")
    p.add_argument("--plate-mm", type=float, default=5.0, help="base plate thickness (default 5)")
    p.add_argument("--pour-mm", type=float, default=8.0, help="pour hole diameter at the highest point (default 8)")
    p.add_argument("--vent-mm", type=float, default=2.0, help="vent diameter (default 2)")
    p.add_argument("--vents", type=int, default=4, help="vents at the next local high points (default 4)")


def run(args: argparse.Namespace) -> int:
    """Export and check the mold; exit 1 when a part fails the checks."""
    from models.errors import ConfigError, SpecError, UsageError
    from offline.cli._common import print_mold
    from offline.design.mold import MoldSettings, export_mold

    if args.margin_mm <= 0 or args.plate_mm <= 0 or args.pour_mm <= 0 or args.vent_mm <= 0:
        raise UsageError("--margin-mm, --plate-mm, --pour-mm and --vent-mm must be positive")
    if args.vents < 0:
        raise UsageError("--vents must be 0 or more")
    settings = MoldSettings(margin_mm=args.margin_mm, plate_mm=args.plate_mm, pour_mm=args.pour_mm,
                            vent_mm=args.vent_mm, vents=args.vents)
    try:
        report = export_mold(args.skin, args.out, settings)
    except SpecError:
        raise
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    return print_mold(report, args.out)
