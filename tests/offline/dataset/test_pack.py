"""Dataset packs: lossless round trip, damaged packs refused, the benchmark reads an unpacked pool as the original,
and the FEM pool shipped with the sample head is the one the default benchmark asks for."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError, UsageError
from models.headspec import load_head
from offline.active.data import PoolSettings
from offline.active.pool import load_benchmark_data
from offline.dataset.generate import generate_dataset
from offline.dataset.pack import pack_dataset, read_header, unpack_dataset
from offline.dataset.sampling import sample_poses
from offline.dataset.store import PoseDataset, PoseStore
from offline.dataset.synthetic import SyntheticSpec
from offline.engine import SerialEngine

ROOT = Path(__file__).resolve().parents[3]
HEAD_PATH = ROOT / "heads" / "sample" / "head.toml"
SHIPPED = ROOT / "heads" / "sample" / "al_pool.npz"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    head = load_head(HEAD_PATH)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    spec = SyntheticSpec(tuple(lo), tuple(hi), grid=8, nonconverged_if_sum_above=9.0)
    root = tmp_path_factory.mktemp("packs") / "ds"
    generate_dataset(root, spec, sample_poses(head, 40, seed=1), head=head.name, names=head.actuator_names,
                     units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(), seed=0,
                     sampling={"boundary_prob": 0.25}, progress_stream=None)
    return root


def test_a_pack_unpacks_to_the_same_dataset_and_the_benchmark_reads_it_as_the_original(dataset, tmp_path):
    header = pack_dataset(dataset, tmp_path / "ds.npz", made_by="likeness offline dataset ...")
    original = PoseDataset(dataset)
    assert header["content_hash"] == original.content_hash() and header["n_poses"] == 40
    assert read_header(tmp_path / "ds.npz")["header"]["made_by"] == "likeness offline dataset ..."
    ds = unpack_dataset(tmp_path / "ds.npz", tmp_path / "out")
    assert not (tmp_path / "out" / "poses").exists()
    assert ds.content_hash() == original.content_hash()
    np.testing.assert_array_equal(np.asarray(ds.offsets), np.asarray(original.offsets))
    assert (ds.status < 1).any()  # the non-converged poses travel too
    a = load_benchmark_data(dataset, 0.35)
    b = load_benchmark_data(tmp_path / "out", 0.35)
    for name in ("pool", "policy", "test"):
        assert getattr(a, name).digest() == getattr(b, name).digest()
    assert b.dataset["n_simulated"] == a.dataset["n_simulated"] == 40
    # Unpacking again over the same dataset opens it; over a different one refuses.
    assert unpack_dataset(tmp_path / "ds.npz", tmp_path / "out").content_hash() == original.content_hash()
    np.save(tmp_path / "out" / "actuators.npy", np.asarray(ds.actuators) + 1.0)
    with pytest.raises(SpecError, match="different dataset"):
        unpack_dataset(tmp_path / "ds.npz", tmp_path / "out")


def test_consolidating_an_unpacked_pack_keeps_its_poses(dataset, tmp_path):
    """An unpacked pack has no pose files to gather: consolidating it (as the guard's report does) changes
    nothing."""
    pack_dataset(dataset, tmp_path / "p.npz")
    unpack_dataset(tmp_path / "p.npz", tmp_path / "u")
    before = PoseDataset(tmp_path / "u").content_hash()
    PoseStore(tmp_path / "u").consolidate()
    after = PoseDataset(tmp_path / "u")
    assert after.content_hash() == before == PoseDataset(dataset).content_hash()
    assert len(after.usable) > 0


def test_a_damaged_pack_is_refused_and_leaves_no_dataset_behind(dataset, tmp_path):
    pack_dataset(dataset, tmp_path / "ds.npz")
    with np.load(tmp_path / "ds.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["offset_planes"] = arrays["offset_planes"].copy()
    arrays["offset_planes"][1234] ^= 1  # one bit of one offset
    np.savez_compressed(tmp_path / "bad.npz", **arrays)
    with pytest.raises(SpecError, match="content_hash"):
        unpack_dataset(tmp_path / "bad.npz", tmp_path / "out")
    assert not (tmp_path / "out" / "dataset.json").exists()
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(SpecError, match="not a readable dataset pack"):
        read_header(tmp_path / "junk.npz")
    with zipfile.ZipFile(tmp_path / "empty.npz", "w"):
        pass
    with pytest.raises(SpecError, match="not a readable dataset pack"):
        read_header(tmp_path / "empty.npz")


def test_the_shipped_pool_is_the_default_benchmark_pool_and_unpacks_whole(tmp_path):
    meta = read_header(SHIPPED)
    s = PoolSettings()
    manifest = meta["manifest"]
    assert (manifest["n_poses"], manifest["seed"]) == (s.poses, s.seed)
    assert manifest["sampling"] == {"boundary_prob": s.boundary_prob, "range_fraction": s.range_fraction}
    assert manifest["problem"]["kind"] == "fem" and manifest["head"] == "sample"
    # The shipped poses are the ones the default pool samples: the pack can stand in for simulating them.
    head = load_head(HEAD_PATH)
    ds = unpack_dataset(SHIPPED, tmp_path / "pool")  # checks the content hash
    np.testing.assert_array_equal(ds.actuators, sample_poses(head, s.poses, seed=s.seed,
                                                             boundary_prob=s.boundary_prob,
                                                             range_fraction=s.range_fraction))
    assert len(ds.usable) >= 0.95 * s.poses
    assert meta["header"]["made_by"].startswith("likeness offline dataset ")


def test_the_benchmark_refuses_a_pack_of_another_pool(dataset, tmp_path):
    pack_dataset(dataset, tmp_path / "other.npz")
    cmd = [sys.executable, "-m", "likeness.cli", "offline", "al-benchmark", "--config", str(HEAD_PATH),
           "--out", str(tmp_path / "bench"), "--pool-pack", str(tmp_path / "other.npz")]
    r = subprocess.run(cmd, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode != 0
    assert "holds a different pool" in r.stderr and "--simulate-pool" in r.stderr
    assert not (tmp_path / "bench" / "pool").exists()


#: The packs the sample predictor was trained on, joined in this order (``docs/predictor.md``).
PREDICTOR_PACKS = ("predictor_dataset.npz", "predictor_dataset_ends.npz", "al_pool_c60_quadratic.npz",
                   "predictor_dataset_corners.npz", "predictor_dataset_ends_s5.npz")


def _evaluate_shipped(packs: list[Path], tmp_path: Path) -> subprocess.CompletedProcess:
    sample = ROOT / "heads" / "sample"
    cmd = [sys.executable, "-m", "likeness.cli", "offline", "evaluate", "--predictor",
           str(sample / "predictor.onnx"), "--dataset", *map(str, packs)]
    return subprocess.run(cmd, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin",
                                              "TMPDIR": str(tmp_path)}, capture_output=True, text=True, timeout=600)


def test_the_shipped_predictor_report_is_reproduced_from_the_shipped_dataset_packs(tmp_path):
    """``likeness offline evaluate`` on the packs shipped beside the sample predictor, joined in the documented
    order, recomputes its report exactly; one pack alone is another dataset, and the check says so."""
    sample = ROOT / "heads" / "sample"
    metas = [read_header(sample / name) for name in PREDICTOR_PACKS]
    report = json.loads((sample / "predictor_report.json").read_text())
    assert report["dataset"]["n_poses"] == sum(m["manifest"]["n_poses"] for m in metas)
    assert {m["manifest"]["problem"]["element_order"] for m in metas} == {report["mesh"]["element_order"]}
    r = _evaluate_shipped([sample / name for name in PREDICTOR_PACKS], tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    result = json.loads(r.stdout)
    assert result["matches"] and result["dataset"]["hash"] == report["dataset"]["hash"]
    assert result["test"]["n_poses"] == report["test"]["n_poses"]
    assert not list(tmp_path.glob("likeness-eval-*"))  # the temporary unpacked and joined datasets are removed
    alone = _evaluate_shipped([sample / PREDICTOR_PACKS[0]], tmp_path)
    assert alone.returncode == 1
    assert "dataset.hash" in " ".join(json.loads(alone.stdout)["differences"])


def test_the_unpack_command_writes_the_dataset_and_refuses_another_in_its_folder(dataset, tmp_path, capsys):
    from likeness.cli import main

    pack_dataset(dataset, tmp_path / "ds.npz", made_by="likeness offline dataset --seed 1")
    assert main(["offline", "dataset-unpack", str(tmp_path / "ds.npz"), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert PoseDataset(tmp_path / "out").content_hash() == PoseDataset(dataset).content_hash()
    assert "40 poses" in out and "made by: likeness offline dataset --seed 1" in out
    assert main(["offline", "dataset-unpack", str(SHIPPED), "--out", str(tmp_path / "out")]) == 2
    assert "holds a different dataset" in capsys.readouterr().err


def test_offsets_stored_as_byte_planes_come_back_bit_for_bit():
    from offline.dataset.pack import byte_planes, from_byte_planes

    rng = np.random.default_rng(3)
    a = (rng.normal(size=(7, 5, 3)) * 1e-3).astype(np.float32)
    a.flat[:4] = [np.nan, np.inf, -0.0, np.float32(1e-42)]  # a NaN, an infinity, a signed zero, a subnormal
    back = from_byte_planes(byte_planes(a), a.shape)
    assert back.dtype == np.float32 and back.tobytes() == a.tobytes()
    with pytest.raises(ValueError, match="bytes for an array of shape"):
        from_byte_planes(byte_planes(a)[:-1], a.shape)


def test_a_pack_of_a_clustered_pool_stands_in_for_it_only_with_the_same_clusters(tmp_path):
    """``--pool-pack`` with ``--clusters``: a pack whose manifest records the same clustered sampling is unpacked
    instead of simulating; the shipped i.i.d. pack, or other clusters, are refused by name."""
    from offline.active.benchmark_job import BenchmarkJob, pool_pack, settings_of
    from offline.active.data import clustered_candidates, clustered_policy_rows

    head = load_head(HEAD_PATH)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    job = BenchmarkJob(config=str(HEAD_PATH), out=str(tmp_path / "bench"), pool_poses=60, clusters=4)
    settings = settings_of(job)[0]
    samples = clustered_candidates(head, sample_poses(head, 60, seed=settings.seed,
                                                      boundary_prob=settings.boundary_prob), settings)
    sampling = {"boundary_prob": settings.boundary_prob, "range_fraction": settings.range_fraction,
                "clusters": 4, "cluster_spread": settings.cluster_spread,
                "clustered_policy_rows": clustered_policy_rows(60, settings).tolist()}
    generate_dataset(tmp_path / "ds", SyntheticSpec(tuple(lo), tuple(hi), grid=6), samples, head=head.name,
                     names=head.actuator_names, units=["rad"] * len(lo), lo=lo, hi=hi, engine=SerialEngine(),
                     seed=settings.seed, sampling=sampling, progress_stream=None)
    pack_dataset(tmp_path / "ds", tmp_path / "clustered.npz")
    assert pool_pack(job, settings) is None  # no pack given: simulated
    given = BenchmarkJob(config=str(HEAD_PATH), out="unused", pool_poses=60, clusters=4,
                         pool_pack=str(tmp_path / "clustered.npz"))
    assert pool_pack(given, settings_of(given)[0]) == str(tmp_path / "clustered.npz")
    other = BenchmarkJob(config=str(HEAD_PATH), out="unused", pool_poses=60, clusters=5,
                         pool_pack=str(tmp_path / "clustered.npz"))
    with pytest.raises(UsageError, match="'clusters': 4"):
        pool_pack(other, settings_of(other)[0])
    iid = BenchmarkJob(config=str(HEAD_PATH), out="unused", clusters=60, pool_pack=str(SHIPPED))
    with pytest.raises(UsageError, match="different pool"):
        pool_pack(iid, settings_of(iid)[0])


#: Fresh poses of the sample head, simulated once and never trained, validated or selected on.
FRESH_PACK = "predictor_fresh.npz"


def test_the_fresh_pose_figures_are_reproduced_from_the_shipped_fresh_pack(tmp_path):
    """The goal's fresh poses ship packed: ``likeness offline evaluate --split all`` on them recomputes the record
    ``docs/predictor_capacity/fresh_sample.json`` for the shipped predictor, and none of them is a training pose."""
    sample = ROOT / "heads" / "sample"
    record = json.loads((ROOT / "docs" / "predictor_capacity" / "fresh_sample.json").read_text())
    cmd = [sys.executable, "-m", "likeness.cli", "offline", "evaluate", "--predictor", str(sample / "predictor.onnx"),
           "--dataset", str(sample / FRESH_PACK), "--split", "all", "--worst", "5"]
    r = subprocess.run(cmd, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "TMPDIR": str(tmp_path)},
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    got = json.loads(r.stdout)
    for key in ("n_poses", "max_at"):
        assert got["all"][key] == record["all"][key]
    for key in ("mean_euclidean_um", "p99_euclidean_um", "max_euclidean_um"):
        assert got["all"][key] == pytest.approx(record["all"][key], rel=1e-4)
    strain, recorded = got["all"]["surface_strain"], record["all"]["surface_strain"]
    assert strain["p99_abs"] == pytest.approx(recorded["p99_abs"], rel=1e-4)
    assert [w["pose_index"] for w in got["worst_poses"]] == [w["pose_index"] for w in record["worst_poses"]]
    fresh = PoseDataset(_unpacked(sample / FRESH_PACK, tmp_path / "fresh")).actuators
    for name in PREDICTOR_PACKS:
        trained = PoseDataset(_unpacked(sample / name, tmp_path / name)).actuators
        assert not (np.abs(fresh[:, None, :] - trained[None, :, :]).max(axis=2) < 1e-9).any(), name


def _unpacked(pack: Path, out: Path) -> Path:
    unpack_dataset(pack, out)
    return out
