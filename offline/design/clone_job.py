"""Face cloning as one job (what ``likeness offline clone`` runs): load the head's skin and targets, estimate the
time a run takes, run it resumably and write its report."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import ConfigError
from offline.fem import energy as en
from offline.fem.linsolve import make_solver

from .actuation import simulate
from .clone import CloneRun, CloneSettings
from .clone_report import write_report
from .face import FaceSkin, load_face
from .targets import DEFAULT_TARGETS, check_targets, load_targets


def load_clone_problem(config: str, mesh: str | None, targets_file: str | None,
                       backend: str = "auto", element_order: int = 1) -> tuple[FaceSkin, Mapping[str, Any]]:
    """The head's face skin and the target expressions (``targets_file``, else the default targets);
    :class:`models.errors.ConfigError` naming what is missing or wrong."""
    from models.errors import SpecError

    try:
        face = load_face(config, mesh, backend=backend, element_order=element_order)
        units, _ = face.skin.face_units()
        targets = (load_targets(targets_file, units) if targets_file
                   else check_targets(DEFAULT_TARGETS, units, "default targets"))
    except SpecError:
        raise
    except (FileNotFoundError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    return face, targets


def estimate_seconds(face: FaceSkin, n_targets: int, settings: CloneSettings) -> tuple[float, dict[str, Any]]:
    """A rough time estimate from one timed assembly + factorization and one timed warm-started pose solve (a 1 %
    actuation step from neutral, what a line-search trial costs), scaled by the solves a run typically needs."""
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


def run_clone(face: FaceSkin, targets: Mapping[str, Any], out: str | Path, settings: CloneSettings, *,
              config: str | Path, targets_file: str | None = None, resume: bool = True,
              progress: Callable[[str], None] = lambda line: None) -> dict[str, Any]:
    """Optimize thickness and actuation for the targets (resuming from ``out``'s checkpoint when ``resume``) and
    write the report, error maps and optimized skin into ``out``; returns the report."""
    job = CloneRun(face, targets, out, settings, progress=progress)
    state = job.run(resume=resume)
    head = face.skin.head
    inputs = {"config": Path(config), "linkmap": head.path("linkmap"),
              "skin_vtu": face.mesh_dir / "skin.vtu", "face_units": face.mesh_dir / "face_units.npz",
              "predictor": head.path("predictor"), "skin_guard": head.path("skin_guard"),
              "targets": Path(targets_file) if targets_file else None}
    return write_report(job, state, inputs)
