"""Build a pose dataset of a head (what ``likeness offline dataset`` runs): sample actuator poses, set up the skin
problem (the FEM through the link map, or the analytic test sheet) and an engine, then simulate every pose into a
resumable dataset folder, or, with active learning, only the poses a selector picks batch by batch."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from models.errors import ConfigError, SpecError, UsageError
from models.headspec import HeadSpec, load_head
from offline.dataset.problem import ProblemSpec
from offline.dataset.sampling import sample_poses, sample_ranges
from offline.engine import make_engine

if TYPE_CHECKING:
    from offline.active.policy import Policy


@dataclass(frozen=True)
class DatasetSettings:
    """A dataset run: the head and its skin, how many poses and how they are sampled, the engine, and (``select``
    of ``genlal`` or ``random``) the active-learning budget, batch, initial poses and policy file."""

    config: str
    out: str
    poses: int
    mesh: str | None = None
    linkmap: str | None = None
    synthetic: bool = False
    engine: str = "local"
    workers: int | None = None
    threads_per_worker: int = 1
    seed: int = 0
    boundary_prob: float = 0.25
    range_fraction: float = 1.0
    max_poses: int | None = None
    start: str = "nearest"
    element_order: int = 1
    backend: str = "auto"
    select: str | None = None
    budget: int | None = None
    batch: int = 10
    init: int | None = None
    policy: str | None = None


def problem_spec(settings: DatasetSettings, head: HeadSpec, lo: np.ndarray, hi: np.ndarray,
                 note: TextIO | None = sys.stderr) -> ProblemSpec:
    """The skin problem each pose is solved with: the analytic sheet, or the FEM skin of the head's mesh moved
    through its link map (checked before any pose is solved); ``note`` hears which material stands in for a head
    without ``[skin_material]``."""
    if settings.synthetic and settings.element_order != 1:
        raise UsageError("--element-order applies to the FEM skin, not to --synthetic")
    if settings.synthetic:
        from offline.dataset.synthetic import SyntheticSpec

        return SyntheticSpec(tuple(float(x) for x in lo), tuple(float(x) for x in hi))
    if not settings.mesh:
        raise UsageError("--mesh is required (or --synthetic for the analytic test sheet)")
    linkmap = settings.linkmap or head.path("linkmap")
    if linkmap is None:
        raise UsageError("--linkmap is required: the head config has no paths.linkmap")
    try:
        from offline.dataset.fem_problem import FemSpec, material_fields
    except ImportError as exc:
        raise ConfigError(f"the skin FEM is not available in this installation: {exc}") from exc
    material = head.skin_material()
    spec = FemSpec(config=str(settings.config), mesh=str(settings.mesh), linkmap=str(linkmap),
                   backend=settings.backend, threads=settings.threads_per_worker,
                   element_order=settings.element_order, **material_fields(material))
    if material is None and note is not None:
        print(f"note: {settings.config} has no [skin_material]; simulating with {spec.material_source}", file=note)
    try:
        spec.check()
    except SpecError:
        raise
    except (OSError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc
    return spec


def _policy(settings: DatasetSettings) -> Policy | None:
    """The GEN-LAL policy of ``--select genlal`` (None for ``random`` or no selection); checks the selection's
    options."""
    if settings.select is None:
        if settings.budget is not None or settings.policy is not None:
            raise UsageError("--budget and --policy need --select genlal|random")
        return None
    if settings.budget is None:
        raise UsageError("--select needs --budget (poses to simulate)")
    if settings.select != "genlal":
        return None
    if not settings.policy:
        raise UsageError("--select genlal needs --policy FILE (likeness offline al-benchmark writes DIR/policy.npz)")
    from offline.active.policy import Policy

    try:
        return Policy.load(settings.policy)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


def build_dataset(settings: DatasetSettings, progress_stream: TextIO | None = sys.stderr) -> dict[str, Any]:
    """Generate (or resume) the dataset of ``settings``; returns its summary (``failed``: poses that did not
    converge). KeyboardInterrupt stops it cleanly: in-flight poses are written and the same call resumes."""
    head = load_head(settings.config)
    if settings.poses < 1:
        raise UsageError(f"--poses must be positive, got {settings.poses}")
    try:
        lo, hi = sample_ranges(head, settings.range_fraction)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    spec = problem_spec(settings, head, lo, hi)
    try:
        samples = sample_poses(head, settings.poses, seed=settings.seed, boundary_prob=settings.boundary_prob,
                               range_fraction=settings.range_fraction)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    policy = _policy(settings)
    try:
        engine = make_engine(settings.engine, settings.workers, settings.threads_per_worker)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    rest_pose = None if settings.synthetic else head.neutral_pose  # the FEM skin is at rest at the head's neutral
    sampling = {"boundary_prob": settings.boundary_prob, "range_fraction": settings.range_fraction}
    with engine:
        if settings.select is None:
            from offline.dataset.generate import generate_dataset

            return generate_dataset(
                settings.out, spec, samples, head=head.name, names=head.actuator_names, units=units, lo=lo, hi=hi,
                engine=engine, seed=settings.seed, sampling=sampling, progress_stream=progress_stream,
                max_poses=settings.max_poses, rest_pose=rest_pose, start=settings.start)
        import torch

        from offline.active.loop import grow_dataset

        torch.set_num_threads(1)
        try:
            return grow_dataset(
                settings.out, spec, samples, select=settings.select, budget=settings.budget, batch=settings.batch,
                init=settings.init or settings.batch, policy=policy, head=head.name, names=head.actuator_names,
                units=units, lo=lo, hi=hi, engine=engine, seed=settings.seed, sampling=sampling,
                progress_stream=progress_stream, rest_pose=rest_pose)
        except SpecError:
            raise
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
