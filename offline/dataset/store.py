"""On-disk pose dataset: one file per solved pose plus a manifest, consolidated into memory-mapped arrays.

Layout of a dataset folder::

    dataset.json         manifest: format, head, actuators (name, SI unit, min, max), seed, sampling, problem,
                         optional rest_pose (actuator values where every offset is zero by construction)
    samples.npy          (N, A) planned actuator values, SI (fixed when the run starts; resume keeps them)
    base.npz             vertices (V, 3) base surface (m), faces (F, 3), optional face_unit_names/face_unit_offsets
    poses/pose_NNNNNN.npz  one per solved pose: p (A,), surface (V, 3) float32, converged, iterations, state
    actuators.npy, offsets.npy (N, V, 3) float32, status.npy (N,) int8  consolidated (1 converged, 0 not converged,
                                                                        -1 failed or missing)
    splits.json          train / validation / test pose indices and the seed that made them (``splits``)

``base.npz`` may also hold ``region_names`` and ``vertex_region`` (V,): the surface region of every vertex, used
for per-region errors. A dataset written before splits existed gets them on first use, from its manifest seed.

Every file is written atomically, so a killed run leaves only whole files and resumes by skipping them.
``offsets.npy`` is written and read through ``numpy.lib.format.open_memmap`` so datasets larger than memory work.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import atomic_path, write_bytes
from models.errors import SpecError
from offline.dataset.splits import SPLIT_NAMES, Splits, load_or_assign

FORMAT = "likeness-pose-dataset"
FORMAT_VERSION = 1
STATUS_CONVERGED, STATUS_NOT_CONVERGED, STATUS_FAILED = 1, 0, -1


def atomic_savez(path: Path, **arrays: Any) -> None:
    """``np.savez`` to ``path`` atomically."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    write_bytes(path, buf.getvalue())


def atomic_save_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr)
    write_bytes(path, buf.getvalue())


@dataclass(frozen=True)
class PoseRecord:
    """One solved pose as stored in its file."""

    index: int
    p: np.ndarray
    surface: np.ndarray
    converged: bool
    iterations: int
    state: np.ndarray | None
    seconds: float
    message: str


class PoseStore:
    """Reads and writes the files of one dataset folder (manifest, samples, base, per-pose files)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.poses_dir = self.root / "poses"

    # ------------------------------------------------------------------ creation
    def create(self, manifest: Mapping[str, Any], samples: np.ndarray, base_vertices: np.ndarray, faces: np.ndarray,
               face_unit_names: Sequence[str] = (), face_unit_offsets: np.ndarray | None = None,
               regions: tuple[Sequence[str], np.ndarray] | None = None) -> None:
        """Write manifest, samples, base and splits of a new dataset (refuses a folder holding a different one).

        ``regions`` is (region names, region index (V,) of every surface vertex), stored for per-region errors.
        """
        if (self.root / "dataset.json").exists():
            old = self.manifest()
            for key in ("actuators", "seed", "n_poses", "sampling"):
                if old.get(key) != manifest.get(key):
                    raise SpecError(str(self.root / "dataset.json"), key,
                                    "folder holds a dataset made with different settings; use a new --out",
                                    old.get(key))
            if old.get("start", "nearest") != manifest.get("start", "nearest"):
                raise SpecError(str(self.root / "dataset.json"), "start",
                                f"folder holds a dataset solved from {old.get('start', 'nearest')!r}; resume it with "
                                f"--start {old.get('start', 'nearest')} or use a new --out", manifest.get("start"))
            if "rest_pose" in manifest and "rest_pose" not in old:  # written before rest poses were recorded
                doc = {**old, "rest_pose": manifest["rest_pose"]}
                write_bytes(self.root / "dataset.json", json.dumps(doc, indent=1).encode())
            return
        self.poses_dir.mkdir(parents=True, exist_ok=True)
        extra: dict[str, Any] = {}
        if face_unit_offsets is not None and len(face_unit_names):
            extra = {"face_unit_names": np.array(list(face_unit_names)),
                     "face_unit_offsets": np.asarray(face_unit_offsets, dtype=np.float32)}
        if regions is not None:
            names, labels = regions
            labels = np.asarray(labels, dtype=np.int32)
            bad = labels.min(initial=0) < 0 or labels.max(initial=0) >= len(names)
            if labels.shape != (len(base_vertices),) or bad:
                raise ValueError(f"regions: expected one index < {len(names)} per surface vertex")
            extra.update(region_names=np.array(list(names)), vertex_region=labels)
        atomic_savez(self.root / "base.npz", vertices=np.asarray(base_vertices, dtype=np.float64),
                     faces=np.asarray(faces, dtype=np.int64), **extra)
        atomic_save_npy(self.root / "samples.npy", np.asarray(samples, dtype=np.float64))
        doc = {"format": FORMAT, "format_version": FORMAT_VERSION, **manifest}
        write_bytes(self.root / "dataset.json", json.dumps(doc, indent=1).encode())
        if len(samples) >= 3:  # smaller datasets cannot be split; training refuses them when it asks
            self.splits()

    def splits(self) -> Splits:
        """The stored train / validation / test split (assigned from the manifest seed and written on first use)."""
        return load_or_assign(self.root, len(self.samples()), int(self.manifest().get("seed", 0)))

    def manifest(self) -> dict[str, Any]:
        path = self.root / "dataset.json"
        try:
            doc = json.loads(path.read_text())
        except FileNotFoundError as exc:
            raise SpecError(str(path), "file", "not a pose dataset (no dataset.json)") from exc
        except json.JSONDecodeError as exc:
            raise SpecError(str(path), "json", f"not valid JSON: {exc}") from exc
        if doc.get("format") != FORMAT:
            raise SpecError(str(path), "format", f"expected {FORMAT!r}", doc.get("format"))
        return doc

    def samples(self) -> np.ndarray:
        return np.load(self.root / "samples.npy")

    def base(self) -> dict[str, np.ndarray]:
        with np.load(self.root / "base.npz") as z:
            return {k: z[k] for k in z.files}

    def remove_leftovers(self) -> list[Path]:
        """Delete the temp files a killed run left behind (hidden ``.*.tmp`` beside their targets); returns them.

        Atomic writes go through such temp files, so none of them is ever a finished result. Run it only when no
        other process writes to this dataset.
        """
        removed = []
        for folder in (self.root, self.poses_dir):
            if not folder.is_dir():
                continue
            for f in folder.glob(".*.tmp"):
                if f.is_file():
                    f.unlink(missing_ok=True)
                    removed.append(f)
        return removed

    # ------------------------------------------------------------------ poses
    def pose_path(self, index: int) -> Path:
        return self.poses_dir / f"pose_{index:06d}.npz"

    def done(self) -> set[int]:
        """Indices whose pose file exists (files are atomic, so an existing one is whole)."""
        if not self.poses_dir.is_dir():
            return set()
        out = set()
        for f in self.poses_dir.glob("pose_*.npz"):
            try:
                out.add(int(f.stem[5:]))
            except ValueError:
                continue
        return out

    def write_pose(self, record: PoseRecord) -> Path:
        path = self.pose_path(record.index)
        arrays: dict[str, Any] = {
            "index": np.int64(record.index), "p": np.asarray(record.p, dtype=np.float64),
            "surface": np.asarray(record.surface, dtype=np.float32), "converged": np.bool_(record.converged),
            "iterations": np.int64(record.iterations), "seconds": np.float64(record.seconds),
            "message": np.array(record.message),
        }
        if record.state is not None:
            arrays["state"] = np.asarray(record.state, dtype=np.float64)
        atomic_savez(path, **arrays)
        return path

    def read_pose(self, index: int, with_state: bool = False) -> PoseRecord:
        path = self.pose_path(index)
        with np.load(path) as z:
            return PoseRecord(
                index=int(z["index"]), p=z["p"], surface=z["surface"], converged=bool(z["converged"]),
                iterations=int(z["iterations"]), state=z["state"] if with_state and "state" in z.files else None,
                seconds=float(z["seconds"]), message=str(z["message"]),
            )

    # ------------------------------------------------------------------ consolidation
    def consolidate(self) -> Path:
        """Gather every pose file into ``actuators.npy``, ``offsets.npy`` (memory-mapped) and ``status.npy``.

        A dataset already consolidated with no pose files (an unpacked pack) is left as it is: there is nothing to
        gather, and rewriting it would mark every pose unsolved."""
        if not self.poses_dir.is_dir() and (self.root / "offsets.npy").exists() \
                and (self.root / "status.npy").exists():
            return self.root
        samples = self.samples()
        base = self.base()["vertices"]
        n, v = samples.shape[0], base.shape[0]
        done = self.done()
        status = np.full(n, STATUS_FAILED, dtype=np.int8)
        with atomic_path(self.root / "offsets.npy") as tmp_off:
            offsets = np.lib.format.open_memmap(tmp_off, mode="w+", dtype=np.float32, shape=(n, v, 3))
            for i in range(n):
                if i not in done:
                    offsets[i] = np.nan
                    continue
                rec = self.read_pose(i)
                if rec.surface.shape != (v, 3):
                    raise SpecError(str(self.pose_path(i)), "surface", f"expected shape {(v, 3)}",
                                    rec.surface.shape)
                offsets[i] = rec.surface - base
                status[i] = STATUS_CONVERGED if rec.converged else STATUS_NOT_CONVERGED
            offsets.flush()
            del offsets
        atomic_save_npy(self.root / "actuators.npy", samples)
        atomic_save_npy(self.root / "status.npy", status)
        return self.root


class PoseDataset:
    """A consolidated dataset opened for training: arrays memory-mapped, metadata from the manifest."""

    def __init__(self, root: str | Path) -> None:
        store = PoseStore(root)
        self.root = Path(root)
        self.manifest = store.manifest()
        if not (self.root / "offsets.npy").exists() or not (self.root / "status.npy").exists():
            store.consolidate()
        self.actuators = np.load(self.root / "actuators.npy")
        self.offsets = np.load(self.root / "offsets.npy", mmap_mode="r")
        self.status = np.load(self.root / "status.npy")
        base = store.base()
        self.base_vertices = base["vertices"]
        self.faces = base["faces"]
        self.face_unit_names: tuple[str, ...] = tuple(str(x) for x in base.get("face_unit_names", ()))
        self.face_unit_offsets = base.get("face_unit_offsets")
        acts = self.manifest["actuators"]
        self.names = tuple(a["name"] for a in acts)
        self.units = tuple(a["unit"] for a in acts)
        self.lo = np.array([a["min"] for a in acts], dtype=np.float64)
        self.hi = np.array([a["max"] for a in acts], dtype=np.float64)
        self.head = str(self.manifest.get("head", ""))
        rest = self.manifest.get("rest_pose")
        #: Actuator values (SI) where the surface is at rest (zero offsets by construction), or None if unrecorded.
        self.rest_pose: np.ndarray | None = None if rest is None else np.asarray(rest, dtype=np.float64)
        if self.rest_pose is not None and self.rest_pose.shape != self.lo.shape:
            raise SpecError(str(self.root / "dataset.json"), "rest_pose", f"expected {len(self.lo)} values", rest)
        if self.offsets.shape[0] != self.actuators.shape[0]:
            raise SpecError(str(self.root / "offsets.npy"), "shape", "pose count differs from actuators.npy")
        self._store = store
        self.region_names: tuple[str, ...] = tuple(str(x) for x in base.get("region_names", ()))
        self.vertex_region: np.ndarray | None = base.get("vertex_region")

    @functools.cached_property
    def splits(self) -> Splits:
        """The dataset's train / validation / test split (assigned and stored on first use by an older dataset)."""
        return self._store.splits()

    @property
    def id(self) -> str:
        """The dataset's name: the manifest's ``id`` if it has one, else the folder name."""
        return str(self.manifest.get("id") or self.root.resolve().name)

    def split(self, name: str) -> np.ndarray:
        """Converged pose indices of split ``name`` (train, validation or test)."""
        if name not in SPLIT_NAMES:
            raise ValueError(f"unknown split {name!r}; expected one of {', '.join(SPLIT_NAMES)}")
        return np.intersect1d(self.splits[name], self.usable)

    def content_hash(self) -> str:
        """SHA-256 over what training and evaluation read: actuators, offsets, status, base surface, splits.

        Array bytes are hashed (not file bytes), so rewriting a file with the same content keeps the hash.
        """
        h = hashlib.sha256()
        for name, arr in (("actuators", self.actuators), ("status", self.status),
                          ("base_vertices", self.base_vertices), ("faces", self.faces)):
            a = np.ascontiguousarray(arr)
            h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
            h.update(a.tobytes())
        h.update(f"offsets:{self.offsets.dtype.str}:{self.offsets.shape}".encode())
        for s in range(0, self.offsets.shape[0], 64):
            h.update(np.ascontiguousarray(self.offsets[s:s + 64]).tobytes())
        h.update(json.dumps(self.splits.to_json(), sort_keys=True).encode())
        return "sha256:" + h.hexdigest()

    def planned_samples(self) -> np.ndarray:
        """The sampler's planned values of every pose index, converged or not (``samples.npy``)."""
        return self._store.samples()

    def base_arrays(self) -> dict[str, np.ndarray]:
        """Everything ``base.npz`` holds: the base surface, faces, face units, regions."""
        return self._store.base()

    @property
    def usable(self) -> np.ndarray:
        """Indices of converged poses (the only ones used for training)."""
        return np.flatnonzero(self.status == STATUS_CONVERGED)
