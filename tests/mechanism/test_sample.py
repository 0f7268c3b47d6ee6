"""The sample head's mechanism file gives the link poses of its closed-form linkages, over the whole range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.headspec import load_head
from models.mechanism import SAMPLE_MECHANISM, Mechanism
from tests.mechanism.reference_linkages import orthonormal_corners, sample_linkages
from tests.mechanism.test_file import SAMPLE_HEAD


@pytest.fixture(scope="module")
def head():
    return load_head(SAMPLE_HEAD)


def test_the_file_gives_the_closed_form_poses_to_a_nanometre(head) -> None:
    mech = Mechanism.load(SAMPLE_MECHANISM)
    ref = orthonormal_corners(sample_linkages())
    rng = np.random.default_rng(7)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    names = head.actuator_names
    corners = [np.c_[lo, hi][:, k] for k in (0, 1)]  # both ends of every range, then random poses
    worst = {}
    for x in [*corners, *rng.uniform(lo, hi, (20, len(names)))]:
        q = dict(zip(names, x, strict=True))
        a, b = ref.link_poses(q), mech.link_poses(q)
        for n in a:
            worst[n] = max(worst.get(n, 0.0), float(np.abs(a[n][:3, 3] - b[n][:3, 3]).max()),
                           float(np.abs(a[n][:3, :3] - b[n][:3, :3]).max()) * 0.1)  # rotation at 0.1 m lever
    assert max(worst.values()) < 1e-9, worst
    rest = ref.rest_poses()
    for n, P in mech.rest_poses().items():
        assert np.allclose(P, rest[n], atol=1e-12), n


def test_the_skewed_corner_plane_of_the_old_formulas_differs_by_under_a_millimetre(head) -> None:
    """What making each lip corner's five-bar buildable changed: measured, not assumed."""
    mech = Mechanism.load(SAMPLE_MECHANISM)
    ref = sample_linkages()
    worst = 0.0
    for up in np.radians([-30, 0, 40]):
        for back in np.radians([-30, 0, 40]):
            if abs(up - back) > math.radians(45):
                continue
            q = {"lip_corner_l_up": up, "lip_corner_l_back": back}
            worst = max(worst, float(np.linalg.norm(ref.link_poses(q)["lip_corner_l"][:3, 3]
                                                    - mech.link_poses(q)["lip_corner_l"][:3, 3])))
    assert 1e-5 < worst < 1e-3
