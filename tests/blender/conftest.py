"""Fixtures for the Blender add-on's tests: Blender as a Python module (``bpy``, the ``blender`` extra), skipped with
the reason when it cannot be imported, and a fresh empty scene with the add-on registered for each test."""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"


def require_bpy(module_level: bool = False) -> Any:
    """``bpy``, or skip (the test, or with ``module_level`` the whole module) saying why it cannot be imported."""
    try:
        import bpy
    except ImportError as exc:  # no wheel for this platform or Python, or the extra is not installed
        pytest.skip(f"Blender as a Python module (bpy==5.0.1, Linux and Python 3.11 only) cannot be imported: {exc}",
                    allow_module_level=module_level)
    return bpy


@pytest.fixture
def blender() -> Iterator[Any]:
    """An empty Blender scene with the add-on registered (unregistered afterwards)."""
    bpy = require_bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from studio.blender import addon

    addon.register()
    try:
        yield bpy
    finally:
        addon.unregister()


def write_lrec(path: Path, names: Sequence[str], rows: np.ndarray, tail: bytes = b"") -> Path:
    """A recording file as docs/operations.md defines it: a padded JSON header line, then float64 records."""
    header = {"format": "likeness.recording", "version": 1, "names": list(names), "units": ["deg"] * len(names),
              "columns": 1 + 2 * len(names), "dtype": "<f8", "meta": {}}
    line = json.dumps(header)
    line += " " * (-(len(line) + 1) % 8) + "\n"
    path.write_bytes(line.encode() + np.asarray(rows, dtype="<f8").tobytes() + tail)
    return path
