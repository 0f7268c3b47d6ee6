"""The sample head's virtual mechanism: rigid skull, coupled and carried links, non-linear drives, hard stops."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.headspec import load_head
from models.linkmap import LinkObservations, fit_linkmap
from models.rigid import matrix_to_quat
from sim_hardware.mechanism import sample_mechanism

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
DEG = math.pi / 180


@pytest.fixture(scope="module")
def head():
    return load_head(SAMPLE)


@pytest.fixture(scope="module")
def mech(head):
    return sample_mechanism(head, seed=5)


def test_mechanism_matches_the_sample_head(head, mech) -> None:
    assert set(mech.actuators) == set(head.actuator_names)
    assert set(mech.links) == {link.name for link in head.links}


def test_skull_never_moves_and_links_move_only_with_their_motors(head, mech) -> None:
    rest = mech.link_poses({})
    for a in head.actuators:
        moved = mech.link_poses({a.name: a.max})
        changed = {n for n in rest if not np.allclose(rest[n], moved[n], atol=1e-12)}
        expected = {link.name for link in head.links if a.name in link.actuators}
        assert changed == expected, a.name
    assert np.allclose(mech.link_poses({n: 0.3 for n in head.actuator_names})["skull"], rest["skull"])


def test_lip_corner_is_coupled_and_lower_lip_rides_on_the_jaw(mech) -> None:
    def corner(up: float, back: float) -> np.ndarray:
        return mech.link_poses({"lip_corner_l_up": up, "lip_corner_l_back": back})["lip_corner_l"][:3, 3]

    # a five-bar point is not the sum of the two motors' separate effects
    joint = corner(30 * DEG, 30 * DEG) - corner(0, 0)
    separate = (corner(30 * DEG, 0) - corner(0, 0)) + (corner(0, 30 * DEG) - corner(0, 0))
    assert np.linalg.norm(joint - separate) > 0.05e-3
    jaw_open = mech.transforms({"jaw": 20 * DEG, "lower_lip": mech.zero_error["lower_lip"]})
    assert np.allclose(jaw_open["lower_lip"], jaw_open["jaw"])  # carried rigidly when its own motor is idle


def test_drives_are_nonlinear_and_stop_at_hard_stops(head, mech) -> None:
    from models.rigid import matrix_to_rotvec

    ze = mech.zero_error
    jaw = [matrix_to_rotvec(mech.transforms({"jaw": q * DEG + ze["jaw"]})["jaw"][:3, :3])[0] for q in (0, 10, 20)]
    assert abs((jaw[2] - jaw[1]) - (jaw[1] - jaw[0])) > 0.2 * DEG  # the four-bar rocker: not a straight line
    rest = mech.rest_poses()["upper_lip"][:3, 3]
    s = [float(np.linalg.norm(mech.link_poses({"upper_lip": q * DEG + ze["upper_lip"]})["upper_lip"][:3, 3] - rest))
         for q in (-20, 20)]
    assert abs(s[1] - s[0]) > 1e-5  # the crank-slider travels unequally either side of zero
    _lo, hi = mech.stops["jaw"]
    assert hi > head.actuator("jaw").max  # stops lie beyond the configured travel
    at_stop = mech.link_poses({"jaw": hi + mech.zero_error["jaw"]})["jaw"]
    beyond = mech.link_poses({"jaw": hi + 5 * DEG})["jaw"]
    assert np.allclose(at_stop, beyond)


def test_zero_error_shifts_the_rest_pose(mech) -> None:
    e = mech.zero_error["jaw"]
    assert abs(e) > 0
    assert np.allclose(mech.link_poses({"jaw": e})["jaw"], mech.rest_poses()["jaw"], atol=1e-12)


def test_quadratic_model_bias_is_below_the_tracker_noise(head, mech) -> None:
    """Noise-free dense fit: what a quadratic m(p) cannot represent of the linkages (the model bias)."""
    rng = np.random.default_rng(1)
    names = head.actuator_names
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    X = rng.uniform(lo, hi, (300, len(names)))
    i, j = names.index("lip_corner_l_up"), names.index("lip_corner_l_back")
    X[:, j] = np.clip(X[:, j], X[:, i] - 45 * DEG, X[:, i] + 45 * DEG)
    poses = mech.link_poses_many(names, X)  # every pose at once (tests/mechanism/test_batch.py: as one by one)
    obs = {n: LinkObservations(poses[n][:, :3, 3], matrix_to_quat(poses[n][:, :3, :3]), np.ones(len(X), bool))
           for n in ("jaw", "lower_lip", "lip_corner_l", "lid_l")}
    lm = fit_linkmap(names, [a.neutral for a in head.actuators], (hi - lo) / 2, X, obs)
    for n, fit in lm.links.items():
        assert fit.residual["rms_mm"] < 0.07, n  # tracker noise is 0.2 mm per axis and frame
        assert fit.residual["rms_deg"] < 0.07, n
