"""Fixtures for the Blender add-on's tests: Blender as a Python module (``bpy``, the ``blender`` extra), skipped with
the reason when it cannot be imported, and a fresh empty scene with the add-on registered for each test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"


def _bpy() -> Any:
    try:
        import bpy
    except ImportError as exc:  # no wheel for this platform or Python, or the extra is not installed
        pytest.skip(f"Blender as a Python module (bpy==5.0.1, Linux and Python 3.11 only) cannot be imported: {exc}")
    return bpy


@pytest.fixture
def blender() -> Iterator[Any]:
    """An empty Blender scene with the add-on registered (unregistered afterwards)."""
    bpy = _bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from studio.blender import addon

    addon.register()
    try:
        yield bpy
    finally:
        addon.unregister()
