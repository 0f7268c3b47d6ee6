"""Datasets of one head and skin joined into one, every pose keeping its split: a dataset grown by more poses.

A predictor's dataset grows by simulating more poses (another seed, more of them at the range ends, poses a
selection rule chose) into a second dataset and joining the two. The joined dataset is what training reads; each
pose keeps the split its own dataset gave it, so a pose that was ever test stays test and a predictor trained on the
joined dataset is still judged on poses it never saw. Only datasets of the same physics join: the same actuators and
ranges, the same base surface and face units, the same FEM problem (element order, material, alignment).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.errors import SpecError
from offline.dataset.splits import SPLIT_NAMES, SPLITS_FILE, Splits
from offline.dataset.store import PoseDataset, atomic_save_npy, atomic_savez

#: Problem fields that name where an input was read from, not what it is (the base surface is compared instead).
_LOCATIONS = ("config", "mesh", "linkmap", "backend")


def merge_datasets(sources: Sequence[str | Path], out: str | Path, names: Sequence[str] | None = None) -> PoseDataset:
    """Join the consolidated datasets ``sources`` (in order) into the dataset folder ``out``; returns it opened.
    ``names`` are what errors call the sources (default their paths): the files a user gave, where ``sources`` are
    the folders they were unpacked to.

    Refuses fewer than two sources, sources of different physics (:func:`check_joinable` names the difference) and
    an ``out`` that already holds a dataset. The manifest is the first source's with the pose count, its
    ``sampling`` and ``start`` set to None where the sources differ in them, and a ``merged_from`` list (each
    source's id, content hash, pose count, seed, sampling and start)."""
    if len(sources) < 2:
        raise ValueError(f"need at least two datasets to join, got {len(sources)}")
    out = Path(out)
    if (out / "dataset.json").exists():
        raise SpecError(str(out), "dataset", "already holds a dataset; join into a new folder")
    labels = [str(s) for s in sources] if names is None else [str(n) for n in names]
    if len(labels) != len(sources):
        raise ValueError(f"{len(labels)} names for {len(sources)} datasets")
    parts = [PoseDataset(s) for s in sources]
    for other, label in zip(parts[1:], labels[1:], strict=True):
        check_joinable(parts[0], other, label)
    sizes = [len(p.status) for p in parts]
    starts = np.cumsum([0, *sizes[:-1]])
    splits = Splits(n=int(sum(sizes)), seed=parts[0].splits.seed, fractions=parts[0].splits.fractions,
                    **{name: np.concatenate([p.splits[name] + s for p, s in zip(parts, starts, strict=True)])
                       for name in SPLIT_NAMES})
    manifest: dict[str, Any] = dict(parts[0].manifest)
    manifest["n_poses"] = splits.n
    manifest["id"] = out.name
    for key in ("sampling", "start"):  # one value for the whole dataset only where every source had it
        values = [p.manifest.get(key) for p in parts]
        manifest[key] = values[0] if all(v == values[0] for v in values) else None
    manifest["merged_from"] = [{"id": p.id, "hash": p.content_hash(), "n_poses": n, "seed": p.manifest.get("seed"),
                                "sampling": p.manifest.get("sampling"), "start": p.manifest.get("start")}
                               for p, n in zip(parts, sizes, strict=True)]
    out.mkdir(parents=True, exist_ok=True)
    # arrays first, the manifest last: a folder without dataset.json is not a dataset, so a killed join is redone
    atomic_savez(out / "base.npz", **parts[0].base_arrays())
    atomic_save_npy(out / "samples.npy", np.concatenate([p.planned_samples() for p in parts]))
    atomic_save_npy(out / "actuators.npy", np.concatenate([p.actuators for p in parts]))
    atomic_save_npy(out / "status.npy", np.concatenate([p.status for p in parts]))
    atomic_save_npy(out / "offsets.npy", np.concatenate([np.asarray(p.offsets) for p in parts]))
    write_bytes(out / SPLITS_FILE, json.dumps(splits.to_json()).encode())
    write_bytes(out / "dataset.json", json.dumps(manifest, indent=1).encode())
    return PoseDataset(out)


def check_joinable(a: PoseDataset, b: PoseDataset, where: str) -> None:
    """Raise :class:`SpecError` naming the first thing in which dataset ``b`` (at ``where``) differs from ``a``
    so that their poses would not be of one skin: actuators, ranges, rest pose, base surface, face units, FEM
    problem. The vertices' region labels are not compared: they name where errors are reported, and the joined
    dataset keeps the first source's (their assignment has changed between versions of the dataset command)."""
    checks: list[tuple[str, Any, Any]] = [
        ("actuators", a.names, b.names), ("units", a.units, b.units),
        ("actuator ranges", (a.lo.tolist(), a.hi.tolist()), (b.lo.tolist(), b.hi.tolist())),
        ("head", a.head, b.head),
        ("rest_pose", None if a.rest_pose is None else a.rest_pose.tolist(),
         None if b.rest_pose is None else b.rest_pose.tolist()),
        ("face units", a.face_unit_names, b.face_unit_names),
        ("problem", problem_physics(a.manifest.get("problem")), problem_physics(b.manifest.get("problem")))]
    for what, x, y in checks:
        if x != y:
            raise SpecError(where, what, f"differs from the first dataset's ({_short(x)})", _short(y))
    for what, x, y in (("base surface", a.base_vertices, b.base_vertices), ("faces", a.faces, b.faces),
                       ("face unit offsets", a.face_unit_offsets, b.face_unit_offsets)):
        if (x is None) != (y is None) or (x is not None and not np.array_equal(x, y)):
            raise SpecError(where, what, "differs from the first dataset's")


def problem_physics(problem: Any) -> Any:
    """The problem record without the places its inputs were read from; a missing element order is 1 (linear tets,
    what datasets wrote before the field existed)."""
    if not isinstance(problem, dict):
        return problem
    out = {k: v for k, v in problem.items() if k not in _LOCATIONS}
    if out.get("kind") == "fem":
        out.setdefault("element_order", 1)
    return out


def _short(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 200 else text[:200] + "..."
