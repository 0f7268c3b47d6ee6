"""Train / validation / test splits of a pose dataset: disjoint, fixed by a seed, stored with the dataset.

Training fits on ``train``; early stopping, epoch and hidden-size selection look only at ``validation``; ``test``
is read once, for the final report. The split covers every planned pose index (converged or not), so it does not
change when a resumed run converges more poses; users of a split keep only its converged poses.
``splits.json`` in the dataset folder holds the seed, the fractions and the three index lists.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.errors import SpecError

SPLITS_FILE = "splits.json"
SPLITS_FORMAT = "likeness-pose-splits"
SPLIT_NAMES = ("train", "validation", "test")
#: Default fractions of (train, validation, test).
DEFAULT_FRACTIONS: tuple[float, float, float] = (0.7, 0.15, 0.15)
#: Mixed into the seed so the split stream differs from the sampling stream of the same dataset seed.
_SPLIT_STREAM = 0x5B117


@dataclass(frozen=True)
class Splits:
    """Three disjoint, sorted index arrays over ``n`` poses, with the seed and fractions that made them."""

    n: int
    seed: int
    fractions: tuple[float, float, float]
    train: np.ndarray
    validation: np.ndarray
    test: np.ndarray

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in SPLIT_NAMES:
            raise KeyError(f"unknown split {name!r}; expected one of {', '.join(SPLIT_NAMES)}")
        return getattr(self, name)

    def sizes(self) -> dict[str, int]:
        return {name: len(self[name]) for name in SPLIT_NAMES}

    def to_json(self) -> dict[str, Any]:
        return {"format": SPLITS_FORMAT, "n": self.n, "seed": self.seed, "fractions": dict(zip(SPLIT_NAMES,
                self.fractions, strict=True)), **{name: [int(i) for i in self[name]] for name in SPLIT_NAMES}}


def assign_splits(n: int, seed: int, fractions: Sequence[float] = DEFAULT_FRACTIONS) -> Splits:
    """Split ``n`` pose indices at random (seeded) into train / validation / test by ``fractions``.

    Validation and test each get at least one pose and train keeps at least one, so ``n`` must be at least 3.
    """
    fr = tuple(float(f) for f in fractions)
    if len(fr) != 3 or any(not np.isfinite(f) or f <= 0 for f in fr) or abs(sum(fr) - 1.0) > 1e-9:
        raise ValueError(f"split fractions must be three positive numbers summing to 1, got {fractions}")
    if n < 3:
        raise ValueError(f"need at least 3 poses for train / validation / test splits, got {n}")
    n_val = max(1, round(n * fr[1]))
    n_test = max(1, round(n * fr[2]))
    if n - n_val - n_test < 1:
        raise ValueError(f"{n} poses leave no training pose with fractions {fr}")
    perm = np.random.default_rng([int(seed), _SPLIT_STREAM]).permutation(n)
    return Splits(n=n, seed=int(seed), fractions=fr,  # type: ignore[arg-type]
                  train=np.sort(perm[n_val + n_test:]), validation=np.sort(perm[:n_val]),
                  test=np.sort(perm[n_val:n_val + n_test]))


def splits_from_json(doc: Mapping[str, Any], n: int, path: str) -> Splits:
    """Validate a stored split against a dataset of ``n`` poses: disjoint, complete, in range."""
    if doc.get("format") != SPLITS_FORMAT:
        raise SpecError(path, "format", f"expected {SPLITS_FORMAT!r}", doc.get("format"))
    if doc.get("n") != n:
        raise SpecError(path, "n", f"split made for a different pose count (dataset has {n})", doc.get("n"))
    arrays = {}
    for name in SPLIT_NAMES:
        if not isinstance(doc.get(name), list):
            raise SpecError(path, name, "missing index list")
        arr = np.asarray(doc[name], dtype=np.int64)
        if arr.size and (arr.min() < 0 or arr.max() >= n):
            raise SpecError(path, name, f"indices must lie in [0, {n})", [int(arr.min()), int(arr.max())])
        arrays[name] = np.sort(arr)
    every = np.concatenate(list(arrays.values()))
    if len(np.unique(every)) != len(every):
        raise SpecError(path, "splits", "train, validation and test overlap")
    if len(every) != n:
        raise SpecError(path, "splits", f"cover {len(every)} of {n} poses; every pose must be in one split")
    fr = doc.get("fractions", {})
    return Splits(n=n, seed=int(doc.get("seed", 0)), fractions=tuple(float(fr.get(k, 0.0)) for k in SPLIT_NAMES),
                  **arrays)  # type: ignore[arg-type]


def load_or_assign(root: str | Path, n: int, seed: int, fractions: Sequence[float] = DEFAULT_FRACTIONS) -> Splits:
    """The dataset's stored split; a dataset without one gets it assigned from ``seed`` and written atomically."""
    path = Path(root) / SPLITS_FILE
    if path.exists():
        try:
            doc = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise SpecError(str(path), "json", f"not valid JSON: {exc}") from exc
        return splits_from_json(doc, n, str(path))
    splits = assign_splits(n, seed, fractions)
    write_bytes(path, json.dumps(splits.to_json()).encode())
    return splits
