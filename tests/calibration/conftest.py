"""Shared fixtures: the sample head, its mechanism, and a small calibration run with ideal motors."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.headspec import load_head
from sim_hardware.mechanism import sample_mechanism

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


@pytest.fixture(scope="session")
def sample_head():
    return load_head(SAMPLE)


@pytest.fixture(scope="session")
def sample_mech(sample_head):
    return sample_mechanism(sample_head, seed=5)
