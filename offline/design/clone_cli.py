"""``likeness offline clone``: design a head's skin thickness and actuation to reproduce target expressions.

Writes into ``--out DIR``: ``report.json`` (per target the mean and max surface error before — uniform skin,
actuation optimized — and after — thickness and actuation optimized —, the runtime predictor inverse's error and its
disagreement with the FEM-exact actuation, the strain range reached with the runtime guard's measure, reachability
and proposed link-layout changes for targets not reached, input hashes and settings), ``error_maps/*.png`` (0–4 mm
colour scale), ``thickness.png``, ``skin/`` (the optimized skin, usable by ``likeness offline simulate``,
``dataset`` and ``train``), ``mold/`` (the STL set of ``likeness offline export-mold``, checked) and
``checkpoint.npz`` (a killed run started again with the same arguments resumes).

Every pose is kept inside the skin's validated strain range (``[skin] strain_min``/``strain_max`` of the head,
measured with the runtime guard's measure) by a constraint inside the actuation optimization;
``--no-strain-constraint`` optimizes without it (poses beyond the range are then reported, and pulled back).
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``clone`` subcommand."""
    p = sub.add_parser("clone", help="optimize skin thickness and actuation so the head reproduces target "
                                     "expressions (face cloning)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="head config (e.g. heads/sample/head.toml)")
    p.add_argument("--out", required=True, help="output folder (resumed when it holds a checkpoint)")
    p.add_argument("--mesh", default=None, help="skin mesh folder (default: skin/ beside the config)")
    p.add_argument("--targets", default=None,
                   help='JSON file {"target name": {"faceUnit": weight, ...}, ...} replacing the default targets')
    p.add_argument("--dry-run", action="store_true", help="print the problem size and an estimated time, then stop")
    p.add_argument("--samples", type=int, default=40, help="MLS thickness samples (default 40)")
    p.add_argument("--max-outer", type=int, default=4, help="thickness/actuation alternations at most (default 4)")
    p.add_argument("--min-thickness-mm", type=float, default=3.0)
    p.add_argument("--max-thickness-mm", type=float, default=12.0)
    p.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--threads", type=int, default=1, help="numba kernel threads (default 1)")
    p.add_argument("--backend", default="auto", help="sparse solver: auto, cholmod, pardiso or superlu")
    p.add_argument("--no-strain-constraint", action="store_true",
                   help="optimize actuation without keeping the poses inside the skin's validated strain range "
                        "(poses beyond it are then only reported, and pulled back toward neutral)")
    p.add_argument("--no-mold", action="store_true", help="skip the STL export of the optimized skin's mold")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)
    register_mold(sub)


def estimate_seconds(face, n_targets: int, settings) -> tuple[float, dict]:
    """A rough time estimate from one timed assembly + factorization and one timed warm-started pose solve (a 1 %
    actuation step from neutral, what a line-search trial costs), scaled by the solves a run typically needs."""
    import time

    import numpy as np

    from offline.fem import energy as en
    from offline.fem.linsolve import make_solver

    from .actuation import simulate

    x = np.asarray(face.mesh.nodes)
    bc = face.space.boundary(face.space.neutral)
    solver = make_solver(face.skin.spec.backend)
    times = []
    for _ in range(2):  # the first call compiles kernels, loads the solver library and analyses the pattern
        t0 = time.perf_counter()
        K = en.stiffness(face.mesh, face.skin.material, x)
        free = np.setdiff1d(np.arange(K.shape[0]), bc.dofs)
        solver.factor(K[free][:, free].tocsr())
        times.append(time.perf_counter() - t0)
    problem = face.actuation_problem()
    space = face.space
    x0 = simulate(problem, space.neutral)
    step = space.expand(space.project(space.reduce(space.neutral + 0.01 * (space.hi - space.lo))))
    t0 = time.perf_counter()
    simulate(problem, step, x0)
    t_solve = time.perf_counter() - t0
    # per target: the predictor check (a solve from farther away, ~5 trials' worth), actuation (~3 iterations of
    # ~2 solves), and per outer iteration thickness (~3 iterations of ~2 solves) plus actuation again
    per_target = 5 + 6 + settings.max_outer * 12
    return n_targets * per_target * t_solve, {"newton_iteration_s": times[-1], "pose_solve_s": t_solve,
                                               "free_dofs": int(free.size)}


def run(args: argparse.Namespace) -> int:
    """Run the face cloning (or its dry run)."""
    from pathlib import Path

    from likeness.cli import CliError
    from models.errors import SpecError
    from offline.fem import kernel_threads

    from .clone import CloneRun, CloneSettings
    from .clone_report import write_report
    from .face import load_face
    from .targets import DEFAULT_TARGETS, check_targets, load_targets

    if args.samples < 3:
        raise CliError(f"--samples {args.samples}: must be >= 3")
    if args.max_outer < 1:
        raise CliError(f"--max-outer {args.max_outer}: must be >= 1")
    if not 0 < args.min_thickness_mm < args.max_thickness_mm:
        raise CliError(f"--min-thickness-mm {args.min_thickness_mm} / --max-thickness-mm {args.max_thickness_mm}: "
                       "need 0 < min < max")
    if args.threads < 1:
        raise CliError(f"--threads {args.threads}: must be >= 1")
    try:
        face = load_face(args.config, args.mesh, backend=args.backend)
        units, _ = face.skin.face_units()
        targets = (load_targets(args.targets, units) if args.targets
                   else check_targets(DEFAULT_TARGETS, units, "default targets"))
    except (SpecError, FileNotFoundError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    settings = CloneSettings(n_samples=args.samples, max_outer=args.max_outer, h_min=args.min_thickness_mm * 1e-3,
                             h_max=args.max_thickness_mm * 1e-3, strain_constraint=not args.no_strain_constraint)
    say = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    with kernel_threads(args.threads):
        if args.dry_run:
            est, info = estimate_seconds(face, len(targets), settings)
            print(f"head {face.skin.head.name}: {face.mesh.n_nodes} nodes, {face.mesh.n_tets} tets, "
                  f"{info['free_dofs']} free DoFs, {len(face.outer)} outer-surface vertices matched")
            print(f"{len(targets)} targets: {', '.join(targets)}")
            print("strain constraint: " + ("on (every pose inside [skin] strain_min .. strain_max, the guard's measure)"
                                           if settings.strain_constraint else "off"))
            print(f"{face.space.n_actuators} actuators ({face.space.n_free} independent after groups), "
                  f"{settings.n_samples} thickness samples, up to {settings.max_outer} outer iterations")
            print(f"one Newton iteration (assembly + factorization) {info['newton_iteration_s']:.3f} s, one "
                  f"warm-started pose solve {info['pose_solve_s']:.2f} s; estimated time about {est / 60:.0f} min "
                  f"(rough, and an upper bound: assumes all {settings.max_outer} outer iterations run)")
            return 0
        run_ = CloneRun(face, targets, args.out, settings, progress=say)
        state = run_.run(resume=not args.fresh)
        head = face.skin.head
        inputs = {"config": Path(args.config), "linkmap": head.path("linkmap"),
                  "skin_vtu": face.mesh_dir / "skin.vtu", "face_units": face.mesh_dir / "face_units.npz",
                  "predictor": head.path("predictor"), "skin_guard": head.path("skin_guard"),
                  "targets": Path(args.targets) if args.targets else None}
        report = write_report(run_, state, inputs)
    sm = report["summary"]
    mm = 1e3
    print(f"before (uniform skin, actuation optimized): surface error mean {sm['before']['surface_mean_m'] * mm:.2f} "
          f"mm, max {sm['before']['surface_max_m'] * mm:.2f} mm; strain measure "
          f"{sm['strain_before']['measure_min']:+.1%} .. {sm['strain_before']['measure_max']:+.1%}")
    print(f"after (thickness + actuation): surface error mean {sm['after']['surface_mean_m'] * mm:.2f} mm, "
          f"max {sm['after']['surface_max_m'] * mm:.2f} mm; strain measure "
          f"{sm['strain_after']['measure_min']:+.1%} .. {sm['strain_after']['measure_max']:+.1%} "
          f"(validated {sm['strain_after']['validated_range'][0]:+.0%} .. "
          f"{sm['strain_after']['validated_range'][1]:+.0%})")
    back = sm["after_strain_limited"]["targets_pulled_back"]
    if back:
        print(f"poses pulled back into the validated strain range ({', '.join(back)}): "
              f"mean {sm['after_strain_limited']['surface_mean_m'] * mm:.2f} mm, "
              f"max {sm['after_strain_limited']['surface_max_m'] * mm:.2f} mm")
    if "predictor_inverse" in sm:
        print(f"runtime predictor inverse, simulated: mean {sm['predictor_inverse']['surface_mean_m'] * mm:.2f} mm, "
              f"max {sm['predictor_inverse']['surface_max_m'] * mm:.2f} mm")
    g = sm["goals"]
    print(f"goal mean <= {g['mean_m'] * mm:.2f} mm: {'met' if g['mean_met'] else 'NOT met'}; "
          f"max <= {g['max_m'] * mm:.1f} mm: {'met' if g['max_met'] else 'NOT met'}"
          + (f" (not reached: {', '.join(sm['unreached_targets'])}; see report.json reachability)"
             if sm["unreached_targets"] else ""))
    print(f"-> {Path(args.out) / 'report.json'}")
    if args.no_mold:
        return 0
    from .mold import export_mold

    say("[clone] exporting the mold of the optimized skin (STL, mm) and checking it")
    return _print_mold(export_mold(Path(args.out) / "skin", Path(args.out) / "mold"), Path(args.out) / "mold")


def register_mold(sub: argparse._SubParsersAction) -> None:
    """Add the ``export-mold`` subcommand."""
    from .mold import __doc__ as mold_doc

    p = sub.add_parser("export-mold", help="STL files (mm) of a skin and its two-part casting mold, checked",
                       description=mold_doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--skin", required=True, help="skin folder (skin.vtu + face_units.npz), e.g. CLONE_DIR/skin")
    p.add_argument("--out", required=True, help="output folder for the STL files and mold_report.json")
    p.add_argument("--margin-mm", type=float, default=12.0, help="mold wall around the skin (default 12)")
    p.add_argument("--plate-mm", type=float, default=5.0, help="base plate thickness (default 5)")
    p.add_argument("--pour-mm", type=float, default=8.0, help="pour hole diameter at the highest point (default 8)")
    p.add_argument("--vent-mm", type=float, default=2.0, help="vent diameter (default 2)")
    p.add_argument("--vents", type=int, default=4, help="vents at the next local high points (default 4)")
    p.set_defaults(func=run_mold)


def run_mold(args: argparse.Namespace) -> int:
    """Export and check the mold; exit 1 when a part fails the checks."""
    from likeness.cli import CliError
    from models.errors import SpecError

    from .mold import MoldSettings, export_mold

    if args.margin_mm <= 0 or args.plate_mm <= 0 or args.pour_mm <= 0 or args.vent_mm <= 0:
        raise CliError("--margin-mm, --plate-mm, --pour-mm and --vent-mm must be positive")
    if args.vents < 0:
        raise CliError("--vents must be 0 or more")
    try:
        report = export_mold(args.skin, args.out, MoldSettings(margin_mm=args.margin_mm, plate_mm=args.plate_mm,
                                                               pour_mm=args.pour_mm, vent_mm=args.vent_mm,
                                                               vents=args.vents))
    except (SpecError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    return _print_mold(report, args.out)


def _print_mold(report: dict, out) -> int:
    from pathlib import Path

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
