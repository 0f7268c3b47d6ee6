"""``likeness offline mechanism``: check a head's mechanism file, and draw it over the face at some poses.

- ``check``: load the mechanism the head config names, refuse it with file, key and why, or print its bodies, joints,
  couplers and motors and solve it at each motor's limits.
- ``draw``: a PNG of the mechanism (front and side views) at neutral and at the poses given.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The two steps and their options."""
    gs = p.add_subparsers(dest="mechanism_command", metavar="STEP")
    p.set_defaults(mechanism_help=p.print_help)
    c = gs.add_parser("check", help="load and check the head's mechanism file, solve it at every motor's limits")
    c.add_argument("--config", required=True, type=Path, help="head config TOML ([paths] mechanism)")
    d = gs.add_parser("draw", help="draw the mechanism over the face (PNG)")
    d.add_argument("--config", required=True, type=Path, help="head config TOML ([paths] mechanism)")
    d.add_argument("--pose", action="append", default=[], metavar="NAME=VALUE[,NAME=VALUE...]",
                   help="also draw this pose, config units (degrees); repeatable")
    d.add_argument("--mesh", type=Path, help="skin mesh (.vtu) drawn behind (default: the head's skin/skin.vtu)")
    d.add_argument("--out", required=True, type=Path, help="PNG file")


def run(args: argparse.Namespace) -> int:
    """Run the chosen step; without one, print the command's help (exit 2)."""
    if args.mechanism_command is None:
        args.mechanism_help()
        return 2
    from models.errors import UsageError
    from models.headspec import load_head
    from models.mechanism import Mechanism, load_mechanism

    head = load_head(args.config)
    path = head.path("mechanism")
    if path is None:
        raise UsageError(f"{args.config}: [paths] mechanism names no mechanism file")
    mech = Mechanism(load_mechanism(path))
    mech.check_against(head)
    if args.mechanism_command == "check":
        s = mech.spec
        print(f"{path}: {len(s.bodies)} bodies, {len(s.joints)} joints, {len(s.couplers)} couplers, "
              f"{len(s.motors)} motors, {len(mech.structure.groups)} independent linkages; links: "
              f"{', '.join(s.links)}")
        for a in head.actuators:
            for v in (a.min, a.max):
                mech.link_poses({a.name: v})
        print("solves at every motor's limits: ok")
        return 0
    poses: list[dict[str, float]] = [{}]
    for text in args.pose:
        pose = {}
        for item in text.split(","):
            name, _, value = item.partition("=")
            if name.strip() not in head.actuator_names or not value:
                raise UsageError(f"--pose {text!r}: {item!r} is not NAME=VALUE of an actuator of {head.name!r}")
            pose[name.strip()] = head.actuator(name.strip()).from_config_units(float(value))
        poses.append(pose)
    nodes = None
    mesh = args.mesh or Path(head.source).parent / "skin" / "skin.vtu"
    if mesh.is_file():
        import meshio

        nodes = meshio.read(mesh).points
    from offline.design.mechanism_draw import draw_mechanism

    draw_mechanism(mech, args.out, poses, nodes, title=f"{head.name}: {path.name} (dashed: {'; '.join(args.pose)})"
                   if args.pose else "")
    print(f"mechanism drawing: {args.out}")
    return 0
