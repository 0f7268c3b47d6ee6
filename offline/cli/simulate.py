"""``likeness offline simulate``: solve one quasi-static pose of the skin with the links moved rigidly.

The skull node set is fixed; every link node set of the mesh follows a rigid 4x4 transform (identity for links not
given: their actuators hold them at rest). Transforms come from a JSON file (``--links``), from the compact
``--link NAME=tx,ty,tz,rx,ry,rz`` form (mm and degrees, rotation R = Rz Ry Rx about the node set's rest centroid,
then translation), or from actuator values through a fitted link map (``--actuators ... --linkmap FILE``).
"""

from __future__ import annotations

import argparse

from offline.cli._common import MATERIAL_MODELS


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The mesh, the link motions, the material and the solver's settings."""
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--mesh", required=True, help="mesh directory (with skin.vtu) or a .vtu file")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--links", help="JSON object: link name -> 4x4 transform (metres, applied to rest positions) "
                                     "or [tx,ty,tz,rx,ry,rz] (mm, deg, about the set's centroid)")
    src.add_argument("--link", action="append", metavar="NAME=tx,ty,tz,rx,ry,rz",
                     help="one link's motion in mm and degrees (repeatable)")
    src.add_argument("--actuators", nargs="+", metavar="NAME=VALUE",
                     help="actuator values in config units (deg or mm), mapped to link transforms by --linkmap")
    p.add_argument("--linkmap", help="link map file (models.linkmap) used with --actuators "
                                     "(default: the head's [paths] linkmap)")
    p.add_argument("--head", default=None, help="head config giving actuator units and ranges for --actuators "
                                                "(default: the sample head)")
    p.add_argument("--out", required=True, help="output .vtu: deformed points, point data 'displacement' (m)")
    p.add_argument("--material", choices=MATERIAL_MODELS, default=None,
                   type=lambda t: t.strip().lower().replace("-", "_").replace("neohookean", "neo_hookean"),
                   help="material model (default: the head's [skin_material], else neo_hookean)")
    p.add_argument("--E", type=float, default=None,
                   help="Young's modulus in Pa (default: the head's [skin_material], else 78000)")
    p.add_argument("--nu", type=float, default=None,
                   help="Poisson's ratio (default: the head's [skin_material], else 0.47)")
    p.add_argument("--backend", default="auto", help="sparse solver: auto, cholmod, pardiso or superlu")
    p.add_argument("--load-steps", default="auto", help="load increments: an integer or 'auto' (default)")
    p.add_argument("--max-iterations", type=int, default=30, help="Newton iterations per load step")
    p.add_argument("--tol", type=float, default=1e-6, help="relative force tolerance")


def run(args: argparse.Namespace) -> int:
    """Solve the pose and write the deformed mesh; exit 1 when Newton did not converge."""
    from offline.skin_pose import PoseSettings, simulate_pose

    settings = PoseSettings(
        mesh=args.mesh, out=args.out, links_json=args.links, link_specs=tuple(args.link or ()),
        actuators=tuple(args.actuators or ()), linkmap=args.linkmap, head=args.head, material=args.material,
        E=args.E, nu=args.nu, backend=args.backend, load_steps=args.load_steps, max_iterations=args.max_iterations,
        tol=args.tol)
    return 0 if simulate_pose(settings) else 1
