"""``likeness offline simulate``: solve one quasi-static pose of the skin with the links moved rigidly.

The skull node set is fixed; every link node set of the mesh follows a rigid 4x4 transform (identity for links not
given: their actuators hold them at rest). Transforms come from a JSON file (``--links``), from the compact
``--link NAME=tx,ty,tz,rx,ry,rz`` form (mm and degrees, rotation R = Rz Ry Rx about the node set's rest centroid,
then translation), or from actuator values through a fitted link map (``--actuators ... --linkmap FILE``).
"""

from __future__ import annotations

import argparse

MATERIALS = ("neo_hookean", "mooney_rivlin", "yeoh")  # models.material.MATERIAL_MODELS


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` subcommand."""
    p = sub.add_parser(
        "simulate",
        help="solve one skin pose: skull fixed, link node sets moved rigidly; writes the deformed mesh",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
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
    p.add_argument("--material", choices=MATERIALS, default=None,
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
    p.set_defaults(func=run)


def parse_link_spec(text: str):
    """Parse ``NAME=tx,ty,tz,rx,ry,rz`` (mm, deg) into (name, six floats); raises ValueError naming the problem."""
    import math

    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ValueError(f"--link {text!r}: expected NAME=tx,ty,tz,rx,ry,rz")
    try:
        nums = [float(v) for v in values.split(",")]
    except ValueError as exc:
        raise ValueError(f"--link {text!r}: values must be numbers") from exc
    if len(nums) != 6 or not all(math.isfinite(v) for v in nums):
        raise ValueError(f"--link {text!r}: expected 6 finite numbers (tx,ty,tz mm, rx,ry,rz deg), got {len(nums)}")
    return name, nums


def compact_transform(centroid, motion):
    """4x4 transform for a compact motion (tx,ty,tz in mm, rx,ry,rz in deg; R = Rz Ry Rx about ``centroid``)."""
    import numpy as np

    tx, ty, tz, rx, ry, rz = motion
    ax, ay, az = np.radians([rx, ry, rz])
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    R = Rz @ Ry @ Rx
    c = np.asarray(centroid, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + np.array([tx, ty, tz]) * 1e-3
    return T


def load_links_json(path: str, centroids):
    """Transforms from a links JSON file; each value a 4x4 matrix or a compact 6-vector (mm, deg)."""
    import json
    from pathlib import Path

    import numpy as np

    from likeness.cli import CliError

    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CliError(f"--links {path}: cannot read: {exc}") from exc
    except ValueError as exc:
        raise CliError(f"--links {path}: invalid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise CliError(f"--links {path}: expected a JSON object of link name -> transform")
    out = {}
    for name, value in data.items():
        if name not in centroids:
            raise CliError(f"--links {path}: key {name!r}: not a link node set of the mesh "
                           f"(have {sorted(centroids)})")
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CliError(f"--links {path}: key {name!r}: not numeric: {value!r}") from exc
        if arr.shape == (6,):
            arr = compact_transform(centroids[name], arr)
        elif arr.shape != (4, 4):
            raise CliError(f"--links {path}: key {name!r}: expected a 4x4 matrix or 6 numbers, "
                           f"got shape {arr.shape}")
        if not np.isfinite(arr).all() or not np.allclose(arr[3], [0, 0, 0, 1]):
            raise CliError(f"--links {path}: key {name!r}: last row must be [0, 0, 0, 1] and values finite")
        R = arr[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise CliError(f"--links {path}: key {name!r}: the 3x3 part is not a rotation")
        out[name] = arr
    return out


def default_head() -> str:
    """The bundled sample head's config path."""
    from pathlib import Path

    return str(Path(__file__).resolve().parents[1] / "heads" / "sample" / "head.toml")


def skin_material(args):
    """The material to simulate: the head's ``[skin_material]`` (else E = 78 kPa, nu = 0.47, neo-Hookean), with
    ``--material``, ``--E`` and ``--nu`` overriding its fields."""
    import dataclasses

    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head
    from models.material import SkinMaterial

    head_path = args.head or default_head()
    try:
        base = load_head(head_path).skin_material()
    except SpecError as exc:
        raise CliError(str(exc)) from exc
    if base is None:
        base = SkinMaterial("neo_hookean", 78_000.0, 0.47, source=f"FEM default ({head_path} has no [skin_material])")
    changes = {k: v for k, v in (("model", args.material), ("E", args.E), ("nu", args.nu)) if v is not None}
    if not changes:
        return base
    if "model" in changes and changes["model"] != base.model:
        changes["shape"] = {}
    try:
        return dataclasses.replace(base, **changes, source=base.source + f"; overridden on the command line: "
                                   f"{', '.join(f'{k}={v}' for k, v in changes.items() if k != 'shape')}")
    except ValueError as exc:
        raise CliError(f"--material/--E/--nu: {exc}") from exc


def actuator_transforms(args, link_names):
    """Link transforms from actuator values (config units of ``--head``: deg or mm) through the link map."""
    import math

    from likeness.cli import CliError
    from models.errors import SpecError
    from models.headspec import load_head

    try:
        head = load_head(args.head)
    except (OSError, SpecError) as exc:
        raise CliError(f"--head {args.head}: {exc}") from exc
    linkmap = args.linkmap or head.path("linkmap")
    if linkmap is None:
        raise CliError("--actuators needs --linkmap FILE (the head config names none)")
    values = {}
    for item in args.actuators:
        name, sep, val = item.partition("=")
        name = name.strip()
        try:
            number = float(val)
        except ValueError:
            number = math.nan
        if not sep or not name or not math.isfinite(number):
            raise CliError(f"--actuators {item!r}: expected NAME=VALUE with a finite number")
        if name not in head.actuator_names:
            raise CliError(f"--actuators {item!r}: {name!r} is not an actuator of {args.head} "
                           f"(have {', '.join(head.actuator_names)})")
        spec = head.actuator(name)
        si = spec.from_config_units(number)
        if not spec.min - 1e-12 <= si <= spec.max + 1e-12:
            raise CliError(f"--actuators {item!r}: outside [{spec.to_config_units(spec.min):g}, "
                           f"{spec.to_config_units(spec.max):g}] {spec.unit}")
        values[name] = si
    from models.linkmap import LinkMap

    try:
        transforms = LinkMap.load(linkmap).transforms(values)
    except (OSError, ValueError, KeyError) as exc:
        raise CliError(f"--linkmap {linkmap}: {exc}") from exc
    return {k: v for k, v in transforms.items() if k in link_names}


def run(args: argparse.Namespace) -> int:
    """Load the mesh, build the boundary conditions, solve and write the deformed mesh."""
    import time
    from pathlib import Path

    import numpy as np

    from likeness.cli import CliError
    from offline.fem import (
        NotConverged,
        SolverOptions,
        load_mesh,
        rigid_transform_dirichlet,
        solve_static,
    )
    from offline.fem.linsolve import available_backends

    material_spec = skin_material(args)
    if args.backend not in ("auto", "cholmod", "pardiso", "superlu"):
        raise CliError(f"--backend {args.backend}: choose auto, cholmod, pardiso or superlu")
    if args.backend != "auto" and args.backend not in available_backends():
        raise CliError(f"--backend {args.backend}: not available here (have {available_backends()})")
    load_steps: int | str = args.load_steps
    if load_steps != "auto":
        try:
            load_steps = int(load_steps)
        except ValueError as exc:
            raise CliError(f"--load-steps {args.load_steps!r}: an integer >= 1 or 'auto'") from exc
        if load_steps < 1:
            raise CliError(f"--load-steps {load_steps}: must be >= 1")
    path = Path(args.mesh)
    vtu = path / "skin.vtu" if path.is_dir() else path
    if not vtu.is_file():
        raise CliError(f"--mesh {args.mesh}: no skin.vtu there (build one with `likeness offline mesh`)")
    t0 = time.perf_counter()
    try:
        mesh = load_mesh(vtu)
    except Exception as exc:
        raise CliError(f"--mesh {vtu}: cannot read: {exc}") from exc
    t_load = time.perf_counter() - t0
    if "skull" not in mesh.node_sets or len(mesh.node_sets["skull"]) == 0:
        raise CliError(f"--mesh {vtu}: no 'skull' node set to hold the skin")
    links = [k for k in mesh.node_sets if k != "skull"]
    centroids = {k: mesh.nodes[mesh.node_sets[k]].mean(axis=0) for k in links if len(mesh.node_sets[k])}

    if args.links:
        transforms = load_links_json(args.links, centroids)
    elif args.link:
        transforms = {}
        for spec in args.link:
            try:
                name, motion = parse_link_spec(spec)
            except ValueError as exc:
                raise CliError(str(exc)) from exc
            if name not in centroids:
                raise CliError(f"--link {spec!r}: {name!r} is not a link node set of the mesh "
                               f"(have {sorted(centroids)})")
            transforms[name] = compact_transform(centroids[name], motion)
    else:
        if args.head is None:
            args.head = default_head()
        transforms = actuator_transforms(args, set(centroids))
    full = {k: transforms.get(k, np.eye(4)) for k in links if k in centroids}
    dirichlet = rigid_transform_dirichlet(mesh, full, fixed_sets=["skull"])
    from offline.material.models import MaterialParams

    material = MaterialParams.from_skin_material(material_spec).to_fem_material(material_spec.density)
    print(f"material: {material_spec.model}, E = {material_spec.E:.6g} Pa, nu = {material_spec.nu:g} "
          f"({material_spec.source})")
    opts = SolverOptions(backend=args.backend, tol_force=args.tol, max_iterations=args.max_iterations,
                         load_steps=load_steps, failure_dir=Path(args.out).resolve().parent)
    moved = {k: float(np.abs(T - np.eye(4)).max()) > 0 for k, T in full.items()}
    print(f"mesh {vtu}: {mesh.n_nodes} nodes, {mesh.n_tets} tets; {len(dirichlet.nodes)} constrained nodes; "
          f"moving {[k for k, m in moved.items() if m] or 'nothing'}")
    try:
        result = solve_static(mesh, material, dirichlet, options=opts)
        ok = True
    except NotConverged as exc:
        result = exc.result
        ok = False
        print(f"NOT CONVERGED: {exc}")
        print("  hint: more load steps (--load-steps N) or another backend (--backend superlu) may get through")
    for row in result.log:
        print("  step {step} it {iteration}: energy {energy:.6e} J, residual {residual:.3e} N, alpha {alpha:.3g}"
              "{proj}".format(proj=", projected" if row.get("projected") else "", **row))
    u = result.x - mesh.nodes
    tim = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    print(f"{'converged' if ok else 'stopped'} in {result.iterations} iterations, {result.load_steps} load steps; "
          f"load {t_load:.2f} s, {tim}")
    print(f"max displacement {np.linalg.norm(u, axis=1).max() * 1e3:.3f} mm; "
          f"total reaction {np.round(result.reaction_total(), 4).tolist()} N")
    if not ok:
        print(f"not writing {args.out}: the solve did not converge")
        return 1
    _write_deformed(Path(args.out), mesh, result.x, u)
    print(f"wrote {args.out}")
    return 0


def _write_deformed(out, mesh, x, u) -> None:
    """Write deformed points with displacement and node-set flags as point data, atomically."""
    from offline.fem import TetMesh, save_mesh

    save_mesh(out, TetMesh(x, mesh.tets, mesh.node_sets), point_data={"displacement": u})
