"""Sampling plan: per-actuator sweeps, joint sweeps of coupled motors, random combinations, held-out poses.

Every pose lies within the (possibly discovered, narrower) actuator limits and satisfies the coupled groups'
``max_spread``; coupled motors are swept jointly on a grid of their pair. A fraction of the random poses is
held out from the fit for validation. The plan is deterministic for a seed, and has a hash so a resumed run
can prove it continues the same plan.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from models.headspec import HeadSpec


@dataclass(frozen=True)
class PlannedPose:
    """One pose: index in the plan, SI values for every actuator, its kind and whether it is held out."""

    index: int
    values: dict[str, float]
    kind: str  # "neutral", "sweep", "joint", "random"
    holdout: bool = False


@dataclass(frozen=True)
class Plan:
    """An ordered list of poses over ``actuators``."""

    actuators: tuple[str, ...]
    poses: tuple[PlannedPose, ...]
    seed: int

    def to_dict(self) -> dict:
        return {
            "actuators": list(self.actuators),
            "seed": self.seed,
            "poses": [
                {"index": p.index, "kind": p.kind, "holdout": p.holdout,
                 "values": [p.values[a] for a in self.actuators]}
                for p in self.poses
            ],
        }

    def digest(self) -> str:
        """A hash of the plan's content (actuators, values rounded to 1e-9, kinds)."""
        doc = self.to_dict()
        for p in doc["poses"]:
            p["values"] = [round(v, 9) for v in p["values"]]
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def _satisfies(values: Mapping[str, float], coupled: list[tuple[tuple[str, ...], float]]) -> bool:
    for members, spread in coupled:
        vs = [values[m] for m in members]
        if max(vs) - min(vs) > spread + 1e-12:
            return False
    return True


def make_plan(
    head: HeadSpec,
    samples: int = 120,
    seed: int = 0,
    sweep_levels: int = 5,
    holdout_fraction: float = 0.25,
    limits: Mapping[str, tuple[float, float]] | None = None,
    neutral_every: int = 25,
    tie_groups: bool = False,
) -> Plan:
    """Build the plan for ``head`` (a HeadSpec): sweeps, then ``samples`` random poses (some held out).

    ``limits`` (SI, per actuator) narrows the configured ranges, e.g. to discovered travel limits.
    A neutral pose opens the plan and repeats every ``neutral_every`` poses. With ``tie_groups`` the members of
    ``together``/``mirror`` groups always move as one (value = gain × common value), as the daemon commands
    them; otherwise they are sampled independently, which identifies each link's own motor.
    """
    if samples < 0 or sweep_levels < 2:
        raise ValueError("samples must be >= 0 and sweep_levels >= 2")
    names = tuple(head.actuator_names)
    neutral = {a.name: a.neutral for a in head.actuators}
    lim = {a.name: (a.min, a.max) for a in head.actuators}
    for name, (lo, hi) in dict(limits or {}).items():
        clo, chi = lim[name]
        lim[name] = (max(lo, clo), min(hi, chi))
        neutral[name] = min(max(neutral[name], lim[name][0]), lim[name][1])
    coupled = [(g.actuators, float(g.max_spread)) for g in head.groups if g.kind == "coupled"]
    in_coupled = {m for members, _ in coupled for m in members}
    tied = [(g.actuators, g.gains) for g in head.groups if tie_groups and g.kind in ("together", "mirror")]
    follower = {m: (members[0], gains[k] / gains[0]) for members, gains in tied for k, m in enumerate(members) if k}

    def tie(pose: dict[str, float]) -> dict[str, float]:
        for m, (lead, ratio) in follower.items():
            pose[m] = min(max(ratio * pose[lead], lim[m][0]), lim[m][1])
        return pose

    rng = np.random.default_rng(seed)

    raw: list[tuple[dict[str, float], str]] = []
    for name in names:
        if name in in_coupled or name in follower:
            continue
        lo, hi = lim[name]
        for v in np.linspace(lo, hi, sweep_levels):
            if abs(v - neutral[name]) > 1e-9:
                raw.append((tie({**neutral, name: float(v)}), "sweep"))
    for members, _spread in coupled:
        grids = [np.linspace(*lim[m], sweep_levels) for m in members]
        for combo in np.array(np.meshgrid(*grids, indexing="ij")).reshape(len(members), -1).T:
            pose = {**neutral, **{m: float(v) for m, v in zip(members, combo, strict=True)}}
            if all(abs(pose[m] - neutral[m]) < 1e-12 for m in members):
                continue
            if _satisfies(pose, coupled):
                raw.append((pose, "joint"))
    n_holdout = round(samples * holdout_fraction)
    lo_v = np.array([lim[n][0] for n in names])
    hi_v = np.array([lim[n][1] for n in names])
    drawn = 0
    attempts = 0
    while drawn < samples:
        attempts += 1
        if attempts > 1000 * max(samples, 1):
            raise ValueError("cannot draw random poses satisfying the coupled groups' max_spread")
        vals = tie(dict(zip(names, (float(v) for v in rng.uniform(lo_v, hi_v)), strict=True)))
        if not _satisfies(vals, coupled):
            continue
        raw.append((vals, "random-holdout" if drawn >= samples - n_holdout else "random"))
        drawn += 1

    poses: list[PlannedPose] = []
    for values, kind in [(dict(neutral), "neutral"), *raw]:
        if poses and len(poses) % neutral_every == 0:
            poses.append(PlannedPose(len(poses), dict(neutral), "neutral"))
        holdout = kind == "random-holdout"
        poses.append(PlannedPose(len(poses), values, "random" if holdout else kind, holdout))
    return Plan(names, tuple(poses), seed)
