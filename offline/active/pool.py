"""The labelled data of an active-learning benchmark: a pool to select from, a policy pool and a test set.

All three come from one pose dataset and are disjoint. The test set is the dataset's own ``test`` split (never
selected from, never used to learn or tune anything, read only for the curves). The dataset's train and validation
poses are partitioned once, by a fixed seed, into the benchmark pool (where every method selects) and the policy
pool (where GEN-LAL learns its selection rule by simulated AL runs), so the policy never sees a pool or test pose.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from offline.dataset.store import PoseDataset, PoseStore


@dataclass(frozen=True)
class LabelledSet:
    """Poses with their labels: normalized actuators ``x`` (n, A) in [0, 1], offsets ``y`` (n, V, 3) metres,
    and the dataset pose index of each row."""

    x: np.ndarray
    y: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    def digest(self) -> str:
        """SHA-256 over the rows' indices, actuators and offsets (what the benchmark read)."""
        h = hashlib.sha256()
        for a in (self.index.astype(np.int64), self.x.astype(np.float64), self.y.astype(np.float32)):
            h.update(np.ascontiguousarray(a).tobytes())
        return "sha256:" + h.hexdigest()


@dataclass(frozen=True)
class BenchmarkData:
    """The three disjoint sets of a benchmark, with the base surface (V, 3) and the dataset's identity."""

    pool: LabelledSet
    policy: LabelledSet
    test: LabelledSet
    base: np.ndarray
    dataset: dict
    #: Per policy-pool row: True where it is a clustered candidate (``sampling.clustered_policy_rows`` of the
    #: dataset's manifest); None where the policy pool is i.i.d. throughout.
    policy_clustered: np.ndarray | None = None

    def describe(self) -> dict:
        return {"dataset": self.dataset, "n_pool": len(self.pool), "n_policy": len(self.policy),
                "n_test": len(self.test), "n_vertices": int(self.base.shape[0]),
                "n_actuators": int(self.pool.x.shape[1]),
                "hashes": {"pool": self.pool.digest(), "policy": self.policy.digest(), "test": self.test.digest()}}


def _rows(ds: PoseDataset, idx: np.ndarray) -> LabelledSet:
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    x = (ds.actuators[idx] - ds.lo) / (ds.hi - ds.lo)
    y = np.asarray(ds.offsets[idx], dtype=np.float32)
    return LabelledSet(x=x, y=y, index=idx)


def partition(rest: np.ndarray, policy_fraction: float, partition_seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(policy pool rows, benchmark pool rows) of the dataset's train and validation rows ``rest``."""
    perm = np.random.default_rng([int(partition_seed), 0xA1]).permutation(rest)
    n_policy = round(policy_fraction * len(rest))
    return perm[:n_policy], perm[n_policy:]


def load_benchmark_data(dataset_dir: str | Path, policy_fraction: float = 0.35,
                        partition_seed: int = 0) -> BenchmarkData:
    """Open a dataset and cut it into pool, policy pool and test set (converged poses only).

    A dataset whose run was stopped early is consolidated with what it holds (poses never simulated count as
    missing and are left out of every set; the split of the planned poses does not move). A dataset unpacked from
    a pack (:mod:`offline.dataset.pack`) is already consolidated and has no pose files.
    """
    if not 0.0 < policy_fraction < 1.0:
        raise ValueError(f"policy fraction must lie in (0, 1), got {policy_fraction}")
    store = PoseStore(dataset_dir)
    n_planned = len(store.samples())
    done = len(store.done())
    status_path = Path(dataset_dir) / "status.npy"
    packed = done == 0 and status_path.exists() and (Path(dataset_dir) / "offsets.npy").exists()
    if packed:  # unpacked from a dataset pack: consolidated, no pose files to gather
        done = int((np.load(status_path) >= 0).sum())
    elif done < n_planned and (not status_path.exists() or int((np.load(status_path) >= 0).sum()) != done):
        store.consolidate()
    ds = PoseDataset(dataset_dir)
    test = ds.split("test")
    rest = np.union1d(ds.split("train"), ds.split("validation"))
    policy_rows, pool_rows = partition(rest, policy_fraction, partition_seed)
    n_policy = len(policy_rows)
    if len(test) < 2 or n_policy < 4 or len(rest) - n_policy < 4:
        raise ValueError(f"{dataset_dir}: too few converged poses for a benchmark ({len(rest)} train/validation, "
                         f"{len(test)} test)")
    info = {"id": ds.id, "path": str(dataset_dir), "hash": ds.content_hash(), "head": ds.head,
            "n_poses": len(ds.status), "n_simulated": done, "n_converged": len(ds.usable),
            "problem": ds.manifest.get("problem", {}).get("kind"), "mesh": ds.manifest.get("mesh"),
            "partition": {"policy_fraction": policy_fraction, "seed": partition_seed,
                          "test": "the dataset's test split", "pool_and_policy": "its train and validation splits"}}
    policy = _rows(ds, policy_rows)
    marked = (ds.manifest.get("sampling") or {}).get("clustered_policy_rows")
    clustered = None if not marked else np.isin(policy.index, np.asarray(marked, dtype=np.int64))
    if clustered is not None:
        info["policy_clustered_rows"] = int(clustered.sum())
    return BenchmarkData(pool=_rows(ds, pool_rows), policy=policy, test=_rows(ds, test),
                         base=np.asarray(ds.base_vertices, dtype=np.float64), dataset=info, policy_clustered=clustered)
