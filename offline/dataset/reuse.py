"""Poses another dataset of the same skin problem already solved, taken over instead of solved again.

Re-measuring a strain guard for a new predictor solves the sample performances' poses again, but only the poses
the predictor's inverse produces (the blendshape clip's) change; the actuator clip's poses are the same as before.
A dataset run given an earlier dataset of the same physics copies every planned pose that one solved and
converged, so only the new poses cost FEM time. Physics: the same actuators and ranges, rest pose, FEM problem
(element order, material, alignment), start rule, base surface and faces; the first difference is named.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import SpecError
from offline.dataset.merge import problem_physics
from offline.dataset.store import PoseStore

#: Poses agree when their actuator values agree to this many decimals (SI), as performance poses are deduplicated.
DECIMALS = 9


def check_same_physics(store: PoseStore, source: PoseStore) -> None:
    """Raise :class:`SpecError` naming the first thing in which ``source`` is another skin problem than ``store``."""
    mine, theirs = store.manifest(), source.manifest()
    where = str(source.root)
    for key, norm in (("actuators", _same), ("rest_pose", _same), ("problem", problem_physics),
                      ("n_vertices", _same), ("start", _start)):
        a, b = norm(mine.get(key)), norm(theirs.get(key))
        if a != b:
            raise SpecError(where, key, f"differs from the dataset being made ({_short(a)})", _short(b))
    base_a, base_b = store.base(), source.base()
    for key in ("vertices", "faces"):
        if not np.array_equal(base_a[key], base_b[key]):
            raise SpecError(where, f"base {key}", "differs from the dataset being made")


def reuse_solved(store: PoseStore, source: str | Path, indices: Iterable[int]) -> list[int]:
    """Copy into ``store`` each of its planned poses ``indices`` that the dataset at ``source`` holds solved and
    converged at the same actuator values; returns the indices copied. Each copy keeps the solution (surface,
    state, iterations, time) and takes the planned pose's own index and values."""
    src = PoseStore(source)
    check_same_physics(store, src)
    if not src.poses_dir.is_dir():
        raise SpecError(str(source), "poses", "holds no pose files to take over (an unpacked pack keeps only the "
                        "surfaces, not the solver states a reused pose carries); solve the poses instead")
    by_pose: dict[tuple[float, ...], int] = {}
    for j in sorted(src.done()):
        rec = src.read_pose(j)
        if rec.converged:
            by_pose.setdefault(_key(rec.p), j)
    samples = store.samples()
    copied = []
    for i in indices:
        j = by_pose.get(_key(samples[i]))
        if j is None:
            continue
        rec = src.read_pose(j, with_state=True)
        store.write_pose(replace(rec, index=int(i), p=np.asarray(samples[i], dtype=float)))
        copied.append(int(i))
    return copied


def _key(p: np.ndarray) -> tuple[float, ...]:
    return tuple(np.round(np.asarray(p, dtype=float), DECIMALS).tolist())


def _same(value: Any) -> Any:
    return value


def _start(value: Any) -> Any:
    return value or "nearest"  # datasets written before the field existed were solved from the nearest pose


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 200 else text[:200] + "..."
