"""Channels → actuator targets: the compiled group and actuator mapping gives the numpy reference's targets, for
the sample head's map and one whose groups share members."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from models.kernel_support import kernels_available
from runtime.core.channels import ChannelMap
from runtime.core.solve import SolveState, _channels_numpy, to_targets

HEAD = load_head(Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml")


@pytest.mark.skipif(not kernels_available(), reason="numba is not installed")
def test_compiled_channel_mapping_is_the_numpy_mapping() -> None:
    cm = ChannelMap.build(HEAD)
    assert cm.group_channel.size  # the sample head has group channels
    overlapping = dataclasses.replace(cm, group_channel=np.concatenate([cm.group_channel, [cm.group_channel[0]]]),
                                      group_member=np.concatenate([cm.group_member, [cm.group_member[-1]]]),
                                      group_factor=np.concatenate([cm.group_factor, [-2.0]]))
    rng = np.random.default_rng(2)
    sv = SolveState()
    for m in (cm, overlapping):
        q = np.zeros(m.n_actuators)
        for k in range(500):
            values = rng.normal(0, 20, m.n)
            values[rng.random(m.n) < (0.2 if k % 3 else 0.9)] = np.nan  # some channels, or almost none, addressed
            got = to_targets(sv, m, q, values)
            ref = _channels_numpy(m, values, np.full(m.n_actuators, np.nan))
            assert np.array_equal(got, ref, equal_nan=True), k
