"""``likeness blender``: install the Blender add-on into Blender's user add-on folder, or write it as a zip.

Only the standard library is imported here; the add-on's installer loads when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``install`` (the add-on folder) or ``zip`` (a file for Blender's Install from Disk)."""
    p.description = ("The Blender add-on on the predicted skin (docs/blender.md): 'install' writes it into Blender's "
                     "user add-on folder (then enable 'Likeness' in Preferences > Add-ons), 'zip' writes it as a zip "
                     "for Preferences > Add-ons > Install from Disk.")
    p.add_argument("action", choices=("install", "zip"), help="what to do")
    p.add_argument("--blender-version", default="5.0", metavar="X.Y",
                   help="the Blender version whose user folder receives the add-on (default 5.0)")
    p.add_argument("--target", type=Path, default=None, metavar="DIR",
                   help="install into DIR instead of Blender's user add-on folder (install)")
    p.add_argument("--out", type=Path, default=Path("likeness_blender.zip"), metavar="FILE",
                   help="the zip to write (zip; default ./likeness_blender.zip)")


def run(args: argparse.Namespace) -> int:
    from studio.blender.install import build_zip, install

    if args.action == "install":
        folder = install(args.target, args.blender_version)
        print(f"installed the Likeness add-on in {folder}; enable 'Likeness' in Blender's Preferences > Add-ons")
    else:
        print(f"wrote {build_zip(args.out)}; install it in Blender: Preferences > Add-ons > Install from Disk")
    return 0
