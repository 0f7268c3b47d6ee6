"""Make (or resume) the labelled pose dataset a benchmark runs on, with the project's dataset engine.

The default is FEM poses of the head on its skin mesh, sampled over each actuator's full range (10 % of the values
at a range end, as the sample predictor's dataset): one resumable ``likeness offline dataset`` run, so a killed
benchmark picks the pool up where it stopped. ``--quick`` uses the analytic test sheet (seconds).

With ``clusters`` > 0 the candidate poses (the rows the benchmark pool is cut from) are redundant, as poses taken
from recorded performances are: ``clusters`` centres drawn by the sampler, heavy-tailed cluster sizes (a few
clusters hold most poses, like a neutral face held for long), each pose its centre jittered by ``cluster_spread``
of every actuator's range. The test rows and the policy pool stay the sampler's i.i.d. poses over the range of
use (the policy learns on labelled poses of the range it must serve), so the benchmark measures how well a
selection rule covers the poses the predictor will be asked for from a redundant candidate set.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from offline.dataset.generate import generate_dataset
from offline.dataset.sampling import sample_poses, sample_ranges
from offline.engine import make_engine


@dataclass(frozen=True)
class PoolSettings:
    """What the labelled dataset holds: pose count, sampling seed and settings, the problem (FEM or analytic)."""

    poses: int = 480
    seed: int = 11
    boundary_prob: float = 0.1
    range_fraction: float = 1.0
    synthetic: bool = False
    synthetic_grid: int = 14
    synthetic_stiffening: float = 2.0e4
    #: Poisson ratio replacing the head's skin material's (a changed skin, for the policy-reuse experiment).
    nu: float | None = None
    #: Candidate poses in this many clusters (0: the sampler's i.i.d. poses everywhere); see the module text.
    clusters: int = 0
    cluster_spread: float = 0.05
    policy_fraction: float = 0.35  # the benchmark's, so the clustered rows are the benchmark pool's
    #: FEM pool: 1 the mesh's linear tets, 2 the same tets quadratic (the sample predictor's dataset is quadratic).
    element_order: int = 1


#: Share of the policy pool made of clustered candidates (the rest stays i.i.d.: the policy's pseudo-test poses).
POLICY_CLUSTERED_SHARE = 2 / 3


def _cluster_rows(head, out: np.ndarray, rows: np.ndarray, settings: PoolSettings, salt: int, centre_seed: int) -> None:
    """Replace ``out[rows]`` by poses in ``settings.clusters`` clusters of heavy-tailed sizes (seeded by ``salt``,
    centres drawn by the sampler with ``centre_seed``)."""
    from offline.dataset.sampling import _apply_groups

    rng = np.random.default_rng([settings.seed, salt])
    lo, hi = sample_ranges(head, settings.range_fraction)
    centres = sample_poses(head, settings.clusters, seed=centre_seed, boundary_prob=settings.boundary_prob,
                           range_fraction=settings.range_fraction)
    weight = rng.pareto(1.0, settings.clusters) + 1.0
    which = rng.choice(settings.clusters, size=len(rows), p=weight / weight.sum())
    index = {a.name: i for i, a in enumerate(head.actuators)}
    for r, c in zip(rows, which, strict=True):
        p = np.clip(centres[c] + settings.cluster_spread * (hi - lo) * rng.normal(size=len(lo)), lo, hi)
        _apply_groups(p, head, index, lo, hi)
        out[r] = p


def clustered_policy_rows(n_samples: int, settings: PoolSettings) -> np.ndarray:
    """Dataset rows of the policy pool that hold clustered candidates (a fixed seeded share of it)."""
    from offline.active.pool import partition
    from offline.dataset.splits import assign_splits

    split = assign_splits(n_samples, settings.seed)
    policy_rows = partition(np.union1d(split.train, split.validation), settings.policy_fraction)[0]
    perm = np.random.default_rng([settings.seed, 0xC1A7]).permutation(policy_rows)
    return np.sort(perm[:round(POLICY_CLUSTERED_SHARE * len(perm))])


def clustered_candidates(head, samples: np.ndarray, settings: PoolSettings) -> np.ndarray:
    """``samples`` with the benchmark pool's rows replaced by clustered poses, and a share of the policy pool's
    rows by clustered poses of their own (other centres and sizes: the redundancy the policy must learn to meet);
    test rows and the rest of the policy pool unchanged (i.i.d.)."""
    from offline.active.pool import partition
    from offline.dataset.splits import assign_splits

    split = assign_splits(len(samples), settings.seed)
    rows = partition(np.union1d(split.train, split.validation), settings.policy_fraction)[1]
    out = np.array(samples, dtype=np.float64)
    _cluster_rows(head, out, rows, settings, 0xC1A5, settings.seed + 7717)  # the benchmark pool
    _cluster_rows(head, out, clustered_policy_rows(len(samples), settings), settings, 0xC1A6, settings.seed + 7718)
    return out


def ensure_pool(head, config: str, mesh: str | None, out: str | Path, settings: PoolSettings,
                engine_name: str = "local", workers: int | None = None,
                progress: TextIO | None = sys.stderr) -> dict:
    """Generate the dataset at ``out`` or resume it; returns the dataset generator's summary."""
    lo, hi = sample_ranges(head, settings.range_fraction)
    units = ["rad" if a.kind == "rotary" else "m" for a in head.actuators]
    if settings.synthetic:
        from offline.dataset.synthetic import SyntheticSpec

        spec = SyntheticSpec(tuple(float(v) for v in lo), tuple(float(v) for v in hi), grid=settings.synthetic_grid,
                             stiffening=settings.synthetic_stiffening)
        engine_name = "serial"
    else:
        from offline.dataset.fem_problem import FemSpec, material_fields

        linkmap = head.path("linkmap")
        if mesh is None or linkmap is None:
            raise ValueError("the FEM pool needs a skin mesh and the head's paths.linkmap")
        material = material_fields(head.skin_material())
        if settings.nu is not None:
            if not material:
                raise ValueError("--skin-nu needs the head's [skin_material] to change")
            material["poisson_ratio"] = settings.nu
            material["material_source"] += f"; nu replaced by {settings.nu} for this pool (al-benchmark --skin-nu)"
        spec = FemSpec(config=str(config), mesh=str(mesh), linkmap=str(linkmap),
                       element_order=settings.element_order, **material)
        spec.check()
    samples = sample_poses(head, settings.poses, seed=settings.seed, boundary_prob=settings.boundary_prob,
                           range_fraction=settings.range_fraction)
    sampling = {"boundary_prob": settings.boundary_prob, "range_fraction": settings.range_fraction}
    if settings.clusters:
        samples = clustered_candidates(head, samples, settings)
        sampling.update(clusters=settings.clusters, cluster_spread=settings.cluster_spread,
                        clustered_policy_rows=clustered_policy_rows(len(samples), settings).tolist())
    # The FEM skin is at rest at the head's neutral pose: recorded, as `likeness offline dataset` records it, so a
    # pool can be merged with the predictor's datasets and trained on with the prediction pinned there.
    rest_pose = None if settings.synthetic else head.neutral_pose
    with make_engine(engine_name, workers, 1) as engine:
        return generate_dataset(out, spec, samples, head=head.name, names=head.actuator_names, units=units, lo=lo,
                                hi=hi, engine=engine, seed=settings.seed, sampling=sampling,
                                progress_stream=progress, rest_pose=rest_pose)
