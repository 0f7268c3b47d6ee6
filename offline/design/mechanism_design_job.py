"""Link-layout design as one job (``likeness offline clone --design-mechanism``): actuation on today's mechanism
(the report's "before"), the joint design of layout and actuation, actuation again on the new layout (the "after",
with the strain constraint's full augmented-Lagrangian rounds), then the report and the redesigned head folder.

With an envelope that allows attachment rings, the discrete ring step (:mod:`offline.design.mechanism_design_rings`)
runs between continuous design rounds: screen the ring changes, apply the best, design again, until none improves.

Every stage is checkpointed to ``DIR/layout_checkpoint.npz`` (the design after each accepted iteration, the ring
counts and rounds): a killed run started again with the same arguments resumes; a checkpoint made for other targets,
settings or continuous envelope limits is ignored (one that differs only in the ring limits resumes, its ring step
restarting from the head's own sets when it had changed them under other limits).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from models.mechanism_kin import AssemblyError

from .actuation import TargetResult, optimize_targets, strain_text
from .clone import CloneSettings
from .face import FaceSkin
from .mechanism_design import (
    LayoutProblem,
    LayoutSettings,
    LayoutState,
    design_layout,
    load_checkpoint,
    save_checkpoint,
    settings_json,
)
from .mechanism_design_envelope import DesignSpace, design_space, load_envelope
from .mechanism_design_rings import RingSettings, RingStep, dry_run_lines, screen
from .targets import target_surface

Progress = Callable[[str], None]


def layout_problem(face: FaceSkin, targets: Mapping[str, Mapping[str, float]], envelope: str | Path | None,
                   settings: LayoutSettings, strain: bool = True) -> tuple[LayoutProblem, DesignSpace]:
    """The joint problem of a face, its targets and an envelope file (None: the default envelope)."""
    from models.errors import SpecError
    from models.mechanism import load_mechanism

    head = face.skin.head
    path = head.path("mechanism")
    if path is None:
        raise SpecError(str(head.source) if hasattr(head, "source") else head.name, "paths.mechanism",
                        "the head names no mechanism file; --design-mechanism needs the mechanism as data")
    spec = load_mechanism(path)
    space = design_space(spec, load_envelope(envelope, spec))
    names, offsets = face.skin.face_units()
    rest = np.asarray(face.mesh.nodes)[face.outer]
    surfaces = [target_surface(rest, offsets, names, w) for w in targets.values()]
    return LayoutProblem(face, surfaces, space, settings, strain=strain), space


def _actuation(lp: LayoutProblem, names: list[str], previous: list[TargetResult] | None, label: str,
               iterations: int, say: Progress) -> list[TargetResult]:
    out = []
    for k, name in enumerate(names):
        t0 = time.perf_counter()
        res = optimize_targets(lp.problem, [lp.targets[k]], previous=[previous[k]] if previous else None,
                               starts=[out[-1].p] if out else None, max_iterations=iterations, tol_value=1e-3)[0]
        strain = strain_text(res)
        say(f"[layout] {label} target {k + 1}/{len(names)} {name}: {res.iterations} it, match {res.match:.4g}"
            f"{strain} ({time.perf_counter() - t0:.0f}s)")
        out.append(res)
    return out


def _results(P: np.ndarray, X: np.ndarray, W: np.ndarray) -> list[TargetResult]:
    return [TargetResult(p, x, 0.0, 0.0, 0, True, 0, [], 0.0, strain_weight=float(w))
            for p, x, w in zip(P, X, W, strict=True)]


def _fresh_state(lp: LayoutProblem, space: DesignSpace, arrays: Mapping[str, np.ndarray]) -> LayoutState:
    """The design's start: today's layout, the before stage's actuation and equilibria."""
    con = lp.problem.strain
    w0 = np.maximum(arrays["W_before"], con.weight if con is not None else 0.0)
    return LayoutState(np.zeros(space.size), np.array([lp.aspace.reduce(p) for p in arrays["P_before"]]),
                       list(arrays["X_before"]), w0, [])


def run_layout_design(face: FaceSkin, targets: Mapping[str, Mapping[str, float]], out: str | Path,
                      settings: LayoutSettings, *, config: str | Path, envelope: str | Path | None = None,
                      targets_file: str | None = None, resume: bool = True, write_head_folder: bool = True,
                      map_samples: int = 300, strain: bool = True, rings: RingSettings | None = None,
                      bound: bool = True, progress: Progress = print) -> dict[str, Any]:
    """Run (or resume) the layout design of ``face`` for ``targets`` and write ``out``/report.json, report.md,
    the pictures and ``out/head/``; returns the report. ``rings``: the attachment-ring step's stopping rule;
    ``bound``: also find the attachments' own reach (:mod:`.attachment_bound`), what no layout can beat."""
    from .mechanism_design_report import write_layout_report

    out = Path(out)
    names = list(targets)
    lp, space = layout_problem(face, targets, envelope, settings, strain=strain)
    meta = {"targets": {n: dict(w) for n, w in targets.items()}, "settings": settings_json(settings),
            "envelope": space.envelope.continuous_json(), "variables": list(space.names)}
    if not strain:
        meta["strain_constraint"] = False
    step = RingStep(lp)
    rings = rings if rings is not None else RingSettings()
    ring_meta = json.dumps({"limits": step.limits, "settings": asdict(rings)})
    loaded = load_checkpoint(out, meta) if resume else None
    arrays: dict[str, np.ndarray] = {}
    t_start = time.perf_counter()
    if loaded is not None:
        state, arrays, _info = loaded
        progress(f"[layout] resuming from {out / 'layout_checkpoint.npz'} (iteration {state.iteration}"
                 f"{', design done' if state.done else ''})")
        state, arrays = _resume_rings(lp, space, step, state, arrays, ring_meta, progress)
        try:
            lp.boundary.set_design(state.theta)
        except AssemblyError as exc:
            progress(f"[layout] the checkpoint's design does not assemble over the motors' range ({exc}); "
                     "designing again from today's layout, keeping the before stage")
            arrays = {k: v for k, v in arrays.items() if k.endswith("_before")}
            state = _fresh_state(lp, space, arrays)
            step.set_counts({})
    else:
        progress(f"[layout] before: actuation on today's mechanism, {len(names)} targets")
        before = _actuation(lp, names, None, "before", settings.actuation_iterations, progress)
        arrays = {"P_before": np.array([r.p for r in before]), "X_before": np.array([r.x for r in before]),
                  "W_before": np.array([r.strain_weight for r in before])}
        state = _fresh_state(lp, space, arrays)
        state.seconds = time.perf_counter() - t_start
        save_checkpoint(out, state, meta, arrays)
    progress(f"[layout] design: {space.size} design variables in {len(space.groups)} groups, "
             f"{len(names)} x {lp.aspace.n_free} actuation variables, up to {settings.iterations} iterations"
             + (f"; attachment rings up to {max(step.limits.values())}" if step.active else ""))

    base = state.seconds
    t_mark = time.perf_counter()

    def checkpoint(s: LayoutState) -> None:
        s.seconds = base + time.perf_counter() - t_mark
        save_checkpoint(out, s, meta, arrays)

    state = design_layout(lp, state, progress=progress, checkpoint=checkpoint)
    state.done = True
    checkpoint(state)
    rounds = json.loads(str(arrays["ring_log"])) if "ring_log" in arrays else []
    done = bool(arrays["ring_done"]) if "ring_done" in arrays else not step.active or rings.max_rounds == 0
    while not done:
        progress(f"[rings] round {len(rounds) + 1} (at most {rings.max_rounds})")
        record = screen(step, state, rings, progress)
        rounds.append(record)
        done = not record["applied"] or len(rounds) >= rings.max_rounds
        if record["applied"]:
            for k in ("P_after", "X_after", "W_after"):
                arrays.pop(k, None)
            state.done, state.iteration = False, 0
        arrays.update(ring_counts=step.vector(), ring_log=np.array(json.dumps(rounds, default=float)),
                      ring_done=np.array(done), ring_meta=np.array(ring_meta))
        checkpoint(state)
        if record["applied"]:
            state = design_layout(lp, state, progress=progress, checkpoint=checkpoint)
            state.done = True
            checkpoint(state)
    lp.boundary.set_design(state.theta)
    if "P_after" not in arrays:
        progress("[layout] after: actuation again on the new layout (strain constraint's full rounds)")
        prev = _results(np.array([lp.aspace.expand(z) for z in state.Z]), np.asarray(state.X), state.weights)
        after = _actuation(lp, names, prev, "after", settings.actuation_iterations, progress)
        arrays.update(P_after=np.array([r.p for r in after]), X_after=np.array([r.x for r in after]),
                      W_after=np.array([r.strain_weight for r in after]))
        checkpoint(state)
    if bound and "P_bound" not in arrays:
        arrays.update(_bound(lp, names, arrays, progress))
        checkpoint(state)
    seconds = base + time.perf_counter() - t_mark
    head_dir = out / "head"
    ring_report = {"limits": step.limits, "settings": asdict(rings), "sets": step.summary(), "rounds": rounds,
                   "node_sets": step.node_sets()} if step.active else None
    report = write_layout_report(lp, state, arrays, out, names=names, config=config, targets_file=targets_file,
                                 envelope=envelope, settings=asdict(settings), seconds=seconds,
                                 head_dir=head_dir if write_head_folder else None, map_samples=map_samples,
                                 progress=progress, rings=ring_report)
    return report


def _resume_rings(lp: LayoutProblem, space: DesignSpace, step: RingStep, state: LayoutState,
                  arrays: dict[str, np.ndarray], ring_meta: str, progress: Progress
                  ) -> tuple[LayoutState, dict[str, np.ndarray]]:
    """Put the skin's attachment sets where the checkpoint left them; a checkpoint whose ring step ran under other
    ring limits or settings (and changed a set) designs again from the before stage; one from a run without the
    ring step goes on to it."""
    counts = arrays.get("ring_counts")
    if counts is None:
        return state, arrays
    same = str(arrays.get("ring_meta", "")) == ring_meta
    if not same and np.any(counts):
        progress("[rings] the checkpoint's ring step ran under other ring limits; designing again from today's "
                 "layout, keeping the before stage")
        arrays = {k: v for k, v in arrays.items() if k.endswith("_before")}
        return _fresh_state(lp, space, arrays), arrays
    if not same:
        arrays = {k: v for k, v in arrays.items() if not k.startswith("ring_")}
        return state, arrays
    step.set_counts(np.asarray(counts))
    progress("[rings] attachment sets at " + (", ".join(f"{n} {v:+d}" for n, v in step.counts.items() if v)
                                              or "the head's own"))
    return state, arrays


#: Pose solves per target of the bound stage, typical of the sample head (3 to 96 Gauss-Newton iterations a target,
#: about 300 solves for its 8 targets).
BOUND_SOLVES = 40


def estimate_layout(lp: LayoutProblem, space: DesignSpace, n_targets: int, iterations: int,
                    bound: bool = True) -> dict[str, Any]:
    """Problem size and a rough time estimate: one timed pose solve and one timed design Jacobian, scaled by what
    a run needs (before and after: ~8 solves per target; per iteration: a linearization and ~2 trial solves per
    target; the bound stage: ~BOUND_SOLVES solves per target)."""
    from .actuation import simulate

    x0 = simulate(lp.problem, lp.aspace.neutral)
    p = lp.aspace.expand(lp.aspace.project(lp.aspace.reduce(lp.aspace.neutral + 0.05 * (lp.aspace.hi - lp.aspace.lo))))
    t0 = time.perf_counter()
    simulate(lp.problem, p, x0)
    t_solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    lp.boundary.design_jacobian(p)
    t_jac = time.perf_counter() - t0
    per_it = n_targets * (t_jac + 3 * t_solve)
    bound_s = n_targets * BOUND_SOLVES * t_solve if bound else 0.0
    return {"pose_solve_s": t_solve, "design_jacobian_s": t_jac, "bound_s": bound_s,
            "estimate_s": n_targets * 16 * t_solve + iterations * per_it + bound_s}


def _bound(lp: LayoutProblem, names: list[str], arrays: Mapping[str, np.ndarray],
           say: Progress) -> dict[str, np.ndarray]:
    """The attachments' own reach, each target started from the new layout's solution (the after stage)."""
    from .attachment_bound import attachment_bound, bound_problem

    problem, free = bound_problem(lp.face, strain=lp.problem.strain is not None,
                                  margin=lp.settings.strain_margin, tol_force=lp.settings.tol_force)
    say(f"[bound] the attachments moved freely (6 x {len(free.links)} coordinates a target, no mechanism): the best "
        "any layout could do with these attachment sets")
    starts = []
    for p, x in zip(arrays["P_after"], arrays["X_after"], strict=True):
        T = lp.boundary.transforms(p)
        starts.append(({n: T[n] for n in free.links if n in T}, x))
    res = attachment_bound(problem, free, lp.targets, starts=starts, weights=arrays["W_after"], progress=say,
                           labels=names)
    return {"P_bound": np.array([r.p for r in res]), "X_bound": np.array([r.x for r in res]),
            "bound_links": np.array(json.dumps(list(free.links)))}


def run_layout_command(args: Any, face: FaceSkin, targets: Mapping[str, Mapping[str, float]],
                       say: Progress, thickness: CloneSettings | None = None) -> int:
    """``likeness offline clone --design-mechanism``: the dry run or the run, and its summary lines; with
    ``thickness``, the thickness design on the redesigned head after it (:mod:`.mechanism_thickness`)."""
    from models.errors import UsageError

    if args.design_iterations < 1:
        raise UsageError(f"--design-iterations {args.design_iterations}: must be >= 1")
    settings = LayoutSettings(iterations=args.design_iterations)
    if args.ring_rounds < 0:
        raise UsageError(f"--ring-rounds {args.ring_rounds}: must be >= 0")
    rings = RingSettings(max_rounds=args.ring_rounds)
    if args.dry_run:
        lp, space = layout_problem(face, targets, args.envelope, settings, strain=not args.no_strain_constraint)
        est = estimate_layout(lp, space, len(targets), settings.iterations, bound=not args.no_attachment_bound)
        print(f"head {face.skin.head.name}: {face.mesh.n_nodes} nodes, {face.mesh.n_tets} tets; "
              f"{len(targets)} targets: {', '.join(targets)}")
        print(f"layout design: {space.size} design variables in {len(space.groups)} groups (envelope "
              f"{space.envelope.source}), {lp.aspace.n_free} actuation variables per target, up to "
              f"{settings.iterations} iterations")
        if RingStep(lp).active:
            for line in dry_run_lines(RingStep(lp)):
                print(line)
        print(f"one pose solve {est['pose_solve_s']:.2f} s, one design Jacobian {est['design_jacobian_s']:.2f} s; "
              f"estimated time about {est['estimate_s'] / 60:.0f} min (rough upper bound"
              + (f"; the attachments' own reach about {est['bound_s'] / 60:.0f} min of it" if est["bound_s"] else "")
              + ")")
        return 0
    report = run_layout_design(face, targets, args.out, settings, config=args.config, envelope=args.envelope,
                               targets_file=args.targets, resume=not args.fresh,
                               strain=not args.no_strain_constraint, rings=rings,
                               bound=not args.no_attachment_bound, progress=say)
    sm = report["summary"]
    mm = 1e3
    for label in ("before", "after"):
        v = sm[label]
        print(f"{label}: surface error mean {v['surface_mean_m'] * mm:.2f} mm, max {v['surface_max_m'] * mm:.2f} mm; "
              f"strain {v['strain_min']:+.1%} .. {v['strain_max']:+.1%} "
              f"({'all inside' if v['all_inside_strain_range'] else 'NOT all inside'} the range)")
    if "bound" in sm:
        v = sm["bound"]
        print(f"attachments moved freely (any layout's limit): surface error mean {v['surface_mean_m'] * mm:.2f} mm, "
              f"max {v['surface_max_m'] * mm:.2f} mm")
    g = sm["goal"]
    print(f"goal mean <= 0.5 mm: {'met' if g['mean_met'] else 'NOT met'}; max <= 4 mm: "
          f"{'met' if g['max_met'] else 'NOT met'}" + (f" (not reached: {', '.join(sm['unreached_targets'])}; see "
                                                       "report.md, binding limits)" if sm["unreached_targets"] else ""))
    if thickness is not None:
        from .mechanism_thickness import design_thickness_on_head

        t = design_thickness_on_head(args.out, targets, thickness, targets_file=args.targets, backend=args.backend,
                                     resume=not args.fresh, progress=say)
        dh = t["thickness_change"]
        print(f"thickness on the new layout: surface error mean {t['before']['surface_mean_m'] * mm:.2f} -> "
              f"{t['after']['surface_mean_m'] * mm:.2f} mm, max {t['before']['surface_max_m'] * mm:.2f} -> "
              f"{t['after']['surface_max_m'] * mm:.2f} mm; |dh| mean {dh['abs_mean_mm']:.2f} mm, max "
              f"{dh['abs_max_mm']:.2f} mm ({Path(args.out) / 'thickness' / 'report.json'})")
    print(f"-> {Path(args.out) / 'report.md'}, {Path(args.out) / 'head' / 'head.toml'}")
    return 0
