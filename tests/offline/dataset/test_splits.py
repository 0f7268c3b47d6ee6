"""Dataset splits: disjoint, complete, seeded, stored, assigned once to datasets that predate them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.errors import SpecError
from offline.dataset.splits import SPLITS_FILE, assign_splits, load_or_assign
from offline.dataset.store import PoseStore


def test_assign_is_disjoint_complete_and_seeded():
    s = assign_splits(100, seed=3)
    assert s.sizes() == {"train": 70, "validation": 15, "test": 15}
    every = np.concatenate([s.train, s.validation, s.test])
    assert sorted(every) == list(range(100))
    again = assign_splits(100, seed=3)
    other = assign_splits(100, seed=4)
    assert np.array_equal(s.test, again.test) and not np.array_equal(s.test, other.test)
    tiny = assign_splits(3, seed=0)
    assert tiny.sizes() == {"train": 1, "validation": 1, "test": 1}
    with pytest.raises(ValueError, match="at least 3 poses"):
        assign_splits(2, seed=0)
    with pytest.raises(ValueError, match="summing to 1"):
        assign_splits(10, 0, (0.5, 0.4, 0.2))


def test_old_dataset_gets_splits_once_and_bad_files_are_refused(tmp_path):
    store = PoseStore(tmp_path)
    store.create({"head": "h", "actuators": [], "seed": 7, "n_poses": 20, "sampling": {}},
                 np.zeros((20, 2)), np.zeros((4, 3)), np.zeros((2, 3), dtype=int))
    first = json.loads((tmp_path / SPLITS_FILE).read_text())
    (tmp_path / SPLITS_FILE).unlink()  # as a dataset written before splits existed
    again = store.splits()
    assert again.to_json() == first and again.seed == 7
    mtime = (tmp_path / SPLITS_FILE).stat().st_mtime_ns
    store.splits()
    assert (tmp_path / SPLITS_FILE).stat().st_mtime_ns == mtime  # read, not rewritten
    bad = dict(first, test=first["test"] + first["train"][:1])
    (tmp_path / SPLITS_FILE).write_text(json.dumps(bad))
    with pytest.raises(SpecError, match="overlap"):
        store.splits()
    (tmp_path / SPLITS_FILE).write_text(json.dumps(dict(first, train=first["train"][1:])))
    with pytest.raises(SpecError, match="cover 19 of 20"):
        load_or_assign(tmp_path, 20, 7)
    with pytest.raises(SpecError, match="different pose count"):
        load_or_assign(tmp_path, 21, 7)
