"""A tiny seeded active-learning problem on the analytic sheet: pool, policy pool and test set in memory."""

from __future__ import annotations

import numpy as np
import pytest

from offline.active.learner import LearnerConfig
from offline.active.pool import BenchmarkData, LabelledSet
from offline.dataset.synthetic import SyntheticSpec

N_ACT = 4


def labelled(skin, rng: np.random.Generator, n: int, start: int) -> LabelledSet:
    x = rng.random((n, N_ACT))
    y = np.stack([skin.solve(p, None).surface - skin.base_surface() for p in x]).astype(np.float32)
    return LabelledSet(x=x, y=y, index=np.arange(start, start + n))


@pytest.fixture(scope="session")
def tiny() -> BenchmarkData:
    skin = SyntheticSpec(tuple([0.0] * N_ACT), tuple([1.0] * N_ACT), grid=8).build()
    rng = np.random.default_rng(5)
    return BenchmarkData(pool=labelled(skin, rng, 60, 0), policy=labelled(skin, rng, 40, 60),
                         test=labelled(skin, rng, 30, 100), base=skin.base_surface(), dataset={"id": "tiny"})


@pytest.fixture(scope="session")
def cfg() -> LearnerConfig:
    return LearnerConfig(iterations=25, fine_tune_iterations=4)


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """Small problems: more threads only contend (on a loaded two-core machine, tens of times slower)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
