"""Calibration fits the mechanism (zero offsets, rod lengths, joint positions); the runtime's map agrees with it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.headspec import load_head
from models.linkmap import LinkObservations
from models.mechanism import SAMPLE_MECHANISM, Mechanism, mechanism_from_dict
from models.mechanism_file import with_params
from models.rigid import matrix_to_quat, rotvec_to_matrix
from offline.calibration.mechanism_fit import fit_mechanism, holdout_errors_mm, linkmap_from_mechanism
from tests.mechanism._builders import four_bar
from tests.mechanism.test_file import SAMPLE_HEAD

DEG = math.pi / 180


def _observe(mech: Mechanism, P: np.ndarray, names: list[str], sigma: float, rng) -> dict[str, LinkObservations]:
    poses = [mech.link_poses(dict(zip(names, p, strict=True))) for p in P]
    out = {}
    for n in mech.links:
        pos = np.array([T[n][:3, 3] for T in poses]) + rng.normal(0, sigma, (len(P), 3))
        R = rotvec_to_matrix(rng.normal(0, sigma / 0.03, (len(P), 3))) @ np.array([T[n][:3, :3] for T in poses])
        out[n] = LinkObservations(pos, matrix_to_quat(R), np.ones(len(P), bool))
    return out


def test_the_fit_recovers_zero_offset_and_rod_length() -> None:
    doc = four_bar()
    doc["bodies"]["rocker"]["origin"] = doc["couplers"]["coupler"]["b_point"]  # track the rocker's tip
    design = mechanism_from_dict(doc)
    real = Mechanism(with_params(design, {"couplers.coupler.length": 0.042 + 0.3e-3}), zero_error={"m": 1.5 * DEG})
    rng = np.random.default_rng(2)
    P = rng.uniform(-40 * DEG, 60 * DEG, (30, 1))
    obs = _observe(real, P, ["m"], 0.01e-3, rng)
    fit_obs = {n: LinkObservations(o.positions[:20], o.quaternions[:20], o.valid[:20]) for n, o in obs.items()}
    fit = fit_mechanism(design, ["m"], P[:20], fit_obs, anchors=False)
    assert fit.zero_offsets["m"] == pytest.approx(1.5 * DEG, abs=0.1 * DEG)
    assert fit.params["couplers.coupler.length"][1] == pytest.approx(0.042 + 0.3e-3, abs=0.05e-3)
    hold = {n: LinkObservations(o.positions[20:], o.quaternions[20:], o.valid[20:]) for n, o in obs.items()}
    after = np.concatenate(list(holdout_errors_mm(fit.mechanism, ["m"], P[20:], hold).values()))
    before = np.concatenate(list(holdout_errors_mm(Mechanism(design), ["m"], P[20:], hold).values()))
    # mm: from the design's error down to the noise (0.017 mm 3-D)
    assert np.sqrt(np.mean(after**2)) < 0.03 < 0.3 < np.sqrt(np.mean(before**2))


def test_the_runtime_map_of_the_sample_mechanism_agrees_with_it_within_0_05_mm() -> None:
    head = load_head(SAMPLE_HEAD)
    mech = Mechanism.load(SAMPLE_MECHANISM)
    lm = linkmap_from_mechanism(mech, head, samples=200)
    assert lm.degree == 3
    lm.check_against(head)
    names = list(head.actuator_names)
    rng = np.random.default_rng(11)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    worst = 0.0
    for p in [lo, hi, *rng.uniform(lo, hi, (25, len(names)))]:
        truth, fast = mech.link_poses(dict(zip(names, p, strict=True))), lm.poses(p)
        for n in truth:
            # the frame origin, and a point 30 mm away on the link (its rotation)
            worst = max(worst, float(np.linalg.norm(truth[n][:3, 3] - fast[n][:3, 3])),
                        float(np.linalg.norm((truth[n][:3, :3] - fast[n][:3, :3]) @ [0.03, 0.0, 0.0])))
    assert worst < 0.05e-3, worst


def test_a_map_of_the_highest_degree_a_head_folder_writes_loads_back(tmp_path) -> None:
    """The redesigned head's map may be quintic (MAP_TRIES): the file it writes must load where the head is used."""
    from models.errors import SpecError
    from models.linkmap import MAX_DEGREE, LinkMap
    from offline.design.mechanism_design_head import MAP_TRIES

    head = load_head(SAMPLE_HEAD)
    degree = max(d for d, _ in MAP_TRIES)
    assert degree <= MAX_DEGREE
    lm = linkmap_from_mechanism(Mechanism.load(SAMPLE_MECHANISM), head, samples=120, degree=degree)
    back = LinkMap.load(lm.save(tmp_path / "linkmap.json"))
    p = np.array([a.min + 0.3 * (a.max - a.min) for a in head.actuators])
    assert back.degree == degree
    for n, T in lm.poses(p).items():
        assert np.allclose(back.poses(p)[n], T, atol=1e-12)
    doc = lm.to_dict()
    doc["degree"] = MAX_DEGREE + 1
    with pytest.raises(SpecError, match=f"degree: must be an integer from 2 to {MAX_DEGREE}"):
        LinkMap.from_dict(doc, "linkmap.json")
