"""Joining datasets: every pose and its split kept, training reads the joined dataset, other physics refused."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from models.headspec import load_head
from offline.dataset.generate import generate_dataset
from offline.dataset.merge import merge_datasets
from offline.dataset.sampling import sample_poses
from offline.dataset.store import PoseDataset
from offline.dataset.synthetic import SyntheticSpec
from offline.engine import SerialEngine

ROOT = Path(__file__).resolve().parents[3]
HEAD_PATH = ROOT / "heads" / "sample" / "head.toml"


def _make(root: Path, n: int, seed: int, boundary: float) -> Path:
    head = load_head(HEAD_PATH)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8, nonconverged_if_sum_above=9.0)
    generate_dataset(root, spec, sample_poses(head, n, seed=seed, boundary_prob=boundary), head=head.name,
                     names=head.actuator_names, units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(),
                     seed=seed, sampling={"boundary_prob": boundary}, progress_stream=None)
    PoseDataset(root)  # consolidated
    return root


@pytest.fixture(scope="module")
def two(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("merge")
    return _make(base / "a", 30, seed=1, boundary=0.1), _make(base / "b", 20, seed=2, boundary=0.5)


def test_the_joined_dataset_holds_every_pose_with_its_own_split(two, tmp_path):
    a, b = PoseDataset(two[0]), PoseDataset(two[1])
    m = merge_datasets(two, tmp_path / "ab")
    assert len(m.status) == 50 and m.offsets.shape == (50, *a.offsets.shape[1:])
    np.testing.assert_array_equal(m.actuators, np.concatenate([a.actuators, b.actuators]))
    np.testing.assert_array_equal(np.asarray(m.offsets[30:]), np.asarray(b.offsets))
    np.testing.assert_array_equal(m.status, np.concatenate([a.status, b.status]))
    for name in ("train", "validation", "test"):  # a test pose of either source is a test pose of the join
        np.testing.assert_array_equal(m.splits[name], np.concatenate([a.splits[name], b.splits[name] + 30]))
        np.testing.assert_array_equal(m.split(name), np.concatenate([a.split(name), b.split(name) + 30]))
    froms = m.manifest["merged_from"]
    assert [f["n_poses"] for f in froms] == [30, 20] and froms[1]["hash"] == b.content_hash()
    assert froms[1]["sampling"]["boundary_prob"] == 0.5 and m.manifest["n_poses"] == 50
    assert m.manifest["sampling"] is None  # the sources were sampled differently: no one value describes the join
    with pytest.raises(SpecError, match="already holds a dataset"):
        merge_datasets(two, tmp_path / "ab")


def test_datasets_of_other_physics_are_refused_by_what_differs(two, tmp_path):
    import shutil

    other = tmp_path / "other"
    shutil.copytree(two[1], other)
    doc = json.loads((other / "dataset.json").read_text())
    doc["problem"] = {**doc["problem"], "kind": "fem", "element_order": 2}
    (other / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(SpecError, match="problem"):
        merge_datasets([two[0], other], tmp_path / "x")
    doc["problem"] = json.loads((Path(two[0]) / "dataset.json").read_text())["problem"]
    doc["actuators"][0]["max"] += 0.1
    (other / "dataset.json").write_text(json.dumps(doc))
    with pytest.raises(SpecError, match="actuator ranges"):
        merge_datasets([two[0], other], tmp_path / "y")
    with pytest.raises(ValueError, match="at least two"):
        merge_datasets([two[0]], tmp_path / "z")
    assert not (tmp_path / "x" / "dataset.json").exists() and not (tmp_path / "y" / "dataset.json").exists()


def test_the_command_joins_a_pack_and_a_folder(two, tmp_path):
    from offline.dataset.pack import pack_dataset

    pack_dataset(two[0], tmp_path / "a.npz")
    res = subprocess.run([sys.executable, "-m", "likeness", "offline", "dataset-merge", "--dataset",
                          str(tmp_path / "a.npz"), str(two[1]), "--out", str(tmp_path / "ab")],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "50 poses" in res.stdout and len(PoseDataset(tmp_path / "ab").status) == 50


def test_a_pack_of_other_physics_is_named_as_given_not_by_where_it_was_unpacked(two, tmp_path):
    """Packs are joined from temporary folders; a refusal names the pack the user gave, for the join command and
    for ``evaluate``, which joins its datasets the same way."""
    import shutil

    from offline.dataset.pack import pack_dataset

    other = tmp_path / "other"
    shutil.copytree(two[1], other)
    doc = json.loads((other / "dataset.json").read_text())
    doc["problem"] = {**doc["problem"], "kind": "fem", "element_order": 2}
    (other / "dataset.json").write_text(json.dumps(doc))
    pack_dataset(other, tmp_path / "other.npz")
    for args in (["dataset-merge", "--out", str(tmp_path / "ab")],
                 ["evaluate", "--predictor", str(ROOT / "heads" / "sample" / "predictor.onnx")]):
        res = subprocess.run([sys.executable, "-m", "likeness", "offline", *args, "--dataset", str(two[0]),
                              str(tmp_path / "other.npz")], capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert res.returncode != 0
        assert f"{tmp_path / 'other.npz'}: problem" in res.stderr, res.stderr
    assert not (tmp_path / "ab" / "dataset.json").exists()


def test_the_shipped_quadratic_pool_joins_the_predictors_datasets(tmp_path):
    """The clustered quadratic-tet pool shipped for active learning was solved on the predictor's skin and records the
    head's rest pose, so it joins the predictor's own datasets into one to train on, every pose kept with its split."""
    from offline.dataset.pack import read_header, unpack_dataset

    sample = ROOT / "heads" / "sample"
    head = load_head(HEAD_PATH)
    packs = [sample / "predictor_dataset.npz", sample / "al_pool_c60_quadratic.npz"]
    assert read_header(packs[1])["manifest"]["rest_pose"] == list(head.neutral_pose)
    sizes = [read_header(p)["manifest"]["n_poses"] for p in packs]
    for i, p in enumerate(packs):
        unpack_dataset(p, tmp_path / str(i))
    merged = merge_datasets([tmp_path / "0", tmp_path / "1"], tmp_path / "merged")
    assert len(merged.status) == sum(sizes)
    assert merged.manifest["rest_pose"] == list(head.neutral_pose)
