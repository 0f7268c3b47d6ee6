"""A consolidated pose dataset in one compressed file, to ship with a head or move between machines.

``pack_dataset`` gathers what training and evaluation read (manifest, planned samples, base surface, splits,
actuators, offsets, status) into one ``.npz``; ``unpack_dataset`` writes it back as a consolidated dataset folder
without per-pose files (the sample head's 480-pose FEM pool packs into about 6 MB; the float32 offsets are most of
it and compress little). Since version 2 the offsets are stored byte-planed (the first bytes of every value, then the
second, ...: the exponent bytes of neighbouring values repeat, so the planes compress about a fifth smaller) and
restored bit for bit; version 1 packs are read as before. The pack records the dataset's content hash and
unpacking checks it, so an unpacked dataset is bit for bit what was packed; ``made_by`` records the command that
simulated it.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from models.atomic import write_bytes
from models.errors import SpecError
from offline.dataset.splits import SPLITS_FILE
from offline.dataset.store import PoseDataset, atomic_save_npy, atomic_savez

PACK_FORMAT = "likeness-pose-dataset-pack"
PACK_VERSION = 2
#: Pack versions this code reads (1: offsets stored as plain float32).
READ_VERSIONS = (1, 2)


def byte_planes(a: np.ndarray) -> np.ndarray:
    """The bytes of float32 ``a`` regrouped by position in the value (all first bytes, then all second, ...)."""
    flat = np.ascontiguousarray(a, dtype="<f4").view(np.uint8).reshape(-1, 4)
    return np.ascontiguousarray(flat.T).reshape(-1)


def from_byte_planes(planes: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The float32 array of ``shape`` whose :func:`byte_planes` are ``planes`` (bit for bit)."""
    n = int(np.prod(shape))
    if planes.dtype != np.uint8 or planes.size != 4 * n:
        raise ValueError(f"offset planes hold {planes.size} bytes for an array of shape {tuple(shape)}")
    return np.ascontiguousarray(planes.reshape(4, n).T).view("<f4").reshape(shape).astype(np.float32)


def pack_dataset(dataset_dir: str | Path, out: str | Path, made_by: str = "") -> dict[str, Any]:
    """Write the consolidated dataset at ``dataset_dir`` into the single file ``out`` (atomic); returns its header."""
    ds = PoseDataset(dataset_dir)
    base = ds._store.base()
    header = {"format": PACK_FORMAT, "format_version": PACK_VERSION, "content_hash": ds.content_hash(),
              "n_poses": int(ds.actuators.shape[0]), "n_vertices": int(ds.base_vertices.shape[0]),
              "converged": len(ds.usable), "made_by": made_by}
    arrays = {"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8),
              "manifest": np.frombuffer(json.dumps(ds.manifest).encode(), dtype=np.uint8),
              "splits": np.frombuffer(json.dumps(ds.splits.to_json()).encode(), dtype=np.uint8),
              "samples": ds._store.samples(), "actuators": ds.actuators, "status": ds.status,
              "offset_planes": byte_planes(ds.offsets),
              "offsets_shape": np.asarray(ds.offsets.shape, dtype=np.int64),
              **{f"base_{k}": v for k, v in base.items()}}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_bytes(Path(out), buf.getvalue())
    return header


def read_header(path: str | Path) -> dict[str, Any]:
    """The header and manifest of a pack (``{"header": ..., "manifest": ...}``), without reading the arrays."""
    path = Path(path)
    try:
        with np.load(path) as z:
            header = json.loads(z["header"].tobytes())
            manifest = json.loads(z["manifest"].tobytes())
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise SpecError(str(path), "file", f"not a readable dataset pack: {exc}") from exc
    if header.get("format") != PACK_FORMAT:
        raise SpecError(str(path), "format", f"expected {PACK_FORMAT!r}", header.get("format"))
    if header.get("format_version") not in READ_VERSIONS:
        raise SpecError(str(path), "format_version", f"this version reads {', '.join(map(str, READ_VERSIONS))}",
                        header.get("format_version"))
    return {"header": header, "manifest": manifest}


def unpack_dataset(path: str | Path, out_dir: str | Path) -> PoseDataset:
    """Write the pack at ``path`` as a consolidated dataset folder ``out_dir`` and check its content hash.

    Refuses a folder that already holds a dataset (unless it is this very dataset: then it is opened as is).
    """
    path, out_dir = Path(path), Path(out_dir)
    meta = read_header(path)
    header = meta["header"]
    if (out_dir / "dataset.json").exists():
        ds = PoseDataset(out_dir)
        if ds.content_hash() != header["content_hash"]:
            raise SpecError(str(out_dir), "dataset", f"holds a different dataset than the pack {path}")
        return ds
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    if "offset_planes" in arrays:
        try:
            arrays["offsets"] = from_byte_planes(arrays.pop("offset_planes"),
                                                 tuple(int(v) for v in arrays.pop("offsets_shape")))
        except (KeyError, ValueError) as exc:
            raise SpecError(str(path), "offset_planes", str(exc)) from exc
    out_dir.mkdir(parents=True, exist_ok=True)
    base = {k[5:]: v for k, v in arrays.items() if k.startswith("base_")}
    # Arrays first, the manifest last: a folder without dataset.json is not a dataset, so a killed unpack is redone.
    atomic_savez(out_dir / "base.npz", **base)
    atomic_save_npy(out_dir / "samples.npy", arrays["samples"])
    atomic_save_npy(out_dir / "actuators.npy", arrays["actuators"])
    atomic_save_npy(out_dir / "status.npy", arrays["status"])
    atomic_save_npy(out_dir / "offsets.npy", arrays["offsets"])
    write_bytes(out_dir / SPLITS_FILE, arrays["splits"].tobytes())
    write_bytes(out_dir / "dataset.json", arrays["manifest"].tobytes())
    ds = PoseDataset(out_dir)
    got = ds.content_hash()
    if got != header["content_hash"]:  # a damaged pack: leave no folder that looks like a dataset
        (out_dir / "dataset.json").unlink()
        raise SpecError(str(path), "content_hash", f"unpacked data hash to {got}", header["content_hash"])
    return ds
