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
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from offline.design.clone import CloneSettings
    from offline.design.face import FaceSkin


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The head, the output folder, the targets and the optimization's settings."""
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
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
    p.add_argument("--element-order", type=int, choices=(1, 2), default=1,
                   help="design on linear (1) or quadratic (2) tets: quadratic tets represent the skin's bending "
                        "and bulging through a thin skin (default 1)")
    p.add_argument("--layers", type=int, default=0,
                   help="design on the skin extruded in this many layers of tets through its thickness (written "
                        "to OUT/design_mesh; 0: the skin mesh as it is, default)")
    p.add_argument("--ground-truth-test", action="store_true",
                   help="instead of cloning: recover a random thickness field and random actuations of the head "
                        "from noisy simulated targets (truth on a finer mesh); writes OUT/report.json")
    p.add_argument("--seed", type=int, default=0, help="random seed of the ground-truth test (default 0)")
    p.add_argument("--quick", action="store_true", help="ground-truth test at test size")
    p.add_argument("--noise-mm", type=float, default=0.05,
                   help="ground-truth test: Gaussian noise on the target surfaces, per coordinate (default 0.05)")
    p.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--threads", type=int, default=1, help="numba kernel threads (default 1)")
    p.add_argument("--backend", default="auto", help="sparse solver: auto, cholmod, pardiso or superlu")
    p.add_argument("--no-strain-constraint", action="store_true",
                   help="optimize actuation without keeping the poses inside the skin's validated strain range "
                        "(poses beyond it are then only reported, and pulled back toward neutral)")
    p.add_argument("--no-mold", action="store_true", help="skip the STL export of the optimized skin's mold")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--design-mechanism", action="store_true",
                   help="design the link layout (the mechanism's joint positions, axes, rod lengths and ratios within "
                        "--envelope) together with the actuation, and write DIR/head/, a complete redesigned head "
                        "folder (docs/mechanism.md, layout design); thickness only with --design-thickness")
    p.add_argument("--design-thickness", action="store_true",
                   help="with --design-mechanism: then design the skin's thickness (with actuation) on the redesigned "
                        "head, install the optimized skin in DIR/head/skin and export its mold to DIR/mold "
                        "(the thickness settings above apply; the clone's report in DIR/thickness)")
    p.add_argument("--envelope", default=None,
                   help="mechanical envelope TOML of the layout design (default: joints move <= 15 mm, axes tilt "
                        "<= 20 deg, rod lengths and ratios +-20 %%)")
    p.add_argument("--design-iterations", type=int, default=25,
                   help="layout design: joint Gauss-Newton iterations at most (default 25)")
    p.add_argument("--ring-rounds", type=int, default=3,
                   help="layout design: rounds of the attachment-ring step at most, between continuous rounds "
                        "(default 3; 0: node sets stay as they are); the envelope's attachment_rings limits each set")
    p.add_argument("--no-attachment-bound", action="store_true",
                   help="layout design: skip the attachments' own reach (each attachment set moved freely, no "
                        "mechanism: the best any layout could do with these node sets; about as long as the after "
                        "stage)")


def run(args: argparse.Namespace) -> int:
    """Run the face cloning (or its dry run), print its summary and export the mold."""
    from pathlib import Path

    from models.errors import UsageError
    from offline.cli._common import print_mold
    from offline.design.clone import CloneSettings
    from offline.design.clone_job import load_clone_problem, run_clone
    from offline.design.mold import export_mold
    from offline.fem import kernel_threads

    if args.samples < 3:
        raise UsageError(f"--samples {args.samples}: must be >= 3")
    if args.max_outer < 1:
        raise UsageError(f"--max-outer {args.max_outer}: must be >= 1")
    if not 0 < args.min_thickness_mm < args.max_thickness_mm:
        raise UsageError(f"--min-thickness-mm {args.min_thickness_mm} / --max-thickness-mm "
                         f"{args.max_thickness_mm}: need 0 < min < max")
    if args.threads < 1:
        raise UsageError(f"--threads {args.threads}: must be >= 1")
    if args.design_thickness and not args.design_mechanism:
        raise UsageError("--design-thickness: only with --design-mechanism (without it, clone designs thickness "
                         "anyway)")
    if args.ground_truth_test:
        return _ground_truth(args)
    mesh = args.mesh
    if args.layers:
        from offline.design.layered import layered_skin_folder

        if args.layers < 2:
            raise UsageError(f"--layers {args.layers}: use 2 or more (0: the skin mesh as it is)")
        src = Path(mesh) if mesh else Path(args.config).resolve().parent / "skin"
        mesh = str(Path(args.out) / "design_mesh")
        layered_skin_folder(src, mesh, layers=args.layers)
    face, targets = load_clone_problem(args.config, mesh, args.targets, backend=args.backend,
                                       element_order=args.element_order)
    settings = CloneSettings(n_samples=args.samples, max_outer=args.max_outer, h_min=args.min_thickness_mm * 1e-3,
                             h_max=args.max_thickness_mm * 1e-3, strain_constraint=not args.no_strain_constraint,
                             element_order=args.element_order, layers=args.layers)
    say = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    if args.design_mechanism:
        from offline.design.mechanism_design_job import run_layout_command

        with kernel_threads(args.threads):
            if args.dry_run and args.design_thickness:
                print("then thickness on the redesigned head (estimated on today's head):")
                _print_estimate(face, targets, settings)
            rc = run_layout_command(args, face, targets, say, thickness=settings if args.design_thickness else None)
        if rc or args.dry_run or not args.design_thickness or args.no_mold:
            return rc
        say("[thickness] exporting the mold of the redesigned head's skin (STL, mm) and checking it")
        return print_mold(export_mold(Path(args.out) / "head" / "skin", Path(args.out) / "mold"),
                          Path(args.out) / "mold")
    with kernel_threads(args.threads):
        if args.dry_run:
            _print_estimate(face, targets, settings)
            return 0
        report = run_clone(face, targets, args.out, settings, config=args.config, targets_file=args.targets,
                           resume=not args.fresh, progress=say)
    _print_summary(report["summary"])
    print(f"-> {Path(args.out) / 'report.json'}")
    if args.no_mold:
        return 0
    say("[clone] exporting the mold of the optimized skin (STL, mm) and checking it")
    return print_mold(export_mold(Path(args.out) / "skin", Path(args.out) / "mold"), Path(args.out) / "mold")


def _ground_truth(args: argparse.Namespace) -> int:
    """The head ground-truth test: print its figures against the goals; 0 when every goal is met, else 1."""
    from dataclasses import replace
    from pathlib import Path

    from models.errors import UsageError
    from offline.design.ground_truth_head import HeadTruthSettings, run_head_ground_truth
    from offline.fem import kernel_threads

    if args.noise_mm < 0:
        raise UsageError(f"--noise-mm {args.noise_mm}: must be >= 0")
    settings = replace(HeadTruthSettings.quick() if args.quick else HeadTruthSettings.default(),
                       noise_m=args.noise_mm * 1e-3)
    say = (lambda line: None) if args.quiet else (lambda line: print(line, flush=True))
    with kernel_threads(args.threads):
        r = run_head_ground_truth(args.config, args.out, seed=args.seed, settings=settings, progress=say)
    print(f"thickness relative error over the free skin: max {r['thickness_rel_error_max']:.1%}, mean "
          f"{r['thickness_rel_error_mean']:.1%} (goal 10 % / 3 %)")
    print(f"surface error against the truth: before {r['before']['surface_error_mean_m'] * 1e3:.3f} mm, after "
          f"{r['after']['surface_error_mean_m'] * 1e3:.3f} mm mean (noise {r['noise_m'] * 1e3:.2f} mm; goal 3x)")
    print(f"actuation error: max {r['actuation_error_max']:.2%} of range (goal 1 %)")
    print(f"-> {Path(args.out) / 'report.json'}")
    return 0 if all(r["goals_met"].values()) else 1


def _print_estimate(face: FaceSkin, targets: Mapping[str, Any], settings: CloneSettings) -> None:
    """The problem's size and a rough time estimate (the dry run)."""
    from offline.design.clone_job import estimate_seconds

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


def _print_summary(sm: dict[str, Any]) -> None:
    """Surface errors before and after, the strain range reached, the predictor inverse's error and the goals."""
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
