"""LinkMap m(p): exact recovery of quadratic motion, Jacobian, neutral transforms, file round trip, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.errors import SpecError
from models.headspec import load_head
from models.linkmap import LinkMap, LinkObservations, fit_linkmap, quad_features
from models.rigid import matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotvec_to_matrix, rotvec_to_quat

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
NAMES = ("a", "b", "c")


def truth(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A link moved quadratically by a and b (with a cross term) and not at all by c."""
    t = np.array([0.1 + 0.01 * p[0] + 0.003 * p[0] ** 2, 0.02 * p[1] * p[0] - 0.004 * p[1], 0.05 + 0.002 * p[1] ** 2])
    r = np.array([0.3 * p[0], 0.1 * p[0] * p[1], -0.05 * p[1]])
    return t, rotvec_to_matrix(r) @ rotvec_to_matrix(np.array([0.0, 0.0, 0.5]))


def observations(P: np.ndarray, sigma: float = 0.0, seed: int = 0) -> dict[str, LinkObservations]:
    rng = np.random.default_rng(seed)
    pos, quat = [], []
    for p in P:
        t, R = truth(p)
        pos.append(t + rng.normal(0, sigma, 3) if sigma else t)
        quat.append(matrix_to_quat(R))
    return {"L": LinkObservations(np.array(pos), np.array(quat), np.ones(len(P), dtype=bool))}


@pytest.fixture(scope="module")
def fitted() -> LinkMap:
    rng = np.random.default_rng(1)
    P = rng.uniform(-0.5, 0.5, (80, 3))
    P[0] = 0.0
    return fit_linkmap(NAMES, [0, 0, 0], [0.5, 0.5, 0.5], P, observations(P), head="test")


def test_rigid_helpers_round_trip() -> None:
    rng = np.random.default_rng(0)
    r = rng.normal(0, 0.8, (20, 3))
    R = rotvec_to_matrix(r)
    assert np.allclose(matrix_to_rotvec(R), r, atol=1e-9)
    assert np.allclose(quat_to_matrix(rotvec_to_quat(r)), R, atol=1e-12)
    assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    assert np.allclose(rotvec_to_matrix(r[3]), R[3])  # single fast path agrees with the batch path


def test_fit_detects_actuators_and_is_exact_on_quadratic_motion(fitted: LinkMap) -> None:
    fit = fitted.links["L"]
    assert fit.actuators == ("a", "b")  # b acts partly through a cross term; c does nothing
    assert fit.selection == "data"
    assert fit.residual["rms_mm"] < 1e-6 and fit.residual["rms_deg"] < 1e-6
    p = np.array([0.31, -0.22, 0.4])
    t, R = truth(p)
    P = fitted.poses(dict(zip(NAMES, p, strict=True)))["L"]
    assert np.allclose(P[:3, 3], t, atol=1e-9)
    assert np.allclose(P[:3, :3], R, atol=1e-9)


def test_transforms_are_identity_at_neutral_and_move_points_rigidly(fitted: LinkMap) -> None:
    assert np.allclose(fitted.transforms({})["L"], np.eye(4), atol=1e-12)
    p = {"a": 0.4, "b": -0.3}
    T = fitted.transforms(p)["L"]
    P0, P1 = fitted.poses({})["L"], fitted.poses(p)["L"]
    assert np.allclose(T @ P0, P1, atol=1e-12)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="unknown actuator 'nope'"):
        fitted.transforms({"nope": 1.0})


def test_jacobian_matches_finite_differences(fitted: LinkMap) -> None:
    p0 = np.array([0.1, 0.2, -0.1])
    J = fitted.jacobian(p0)["L"]
    assert J.shape == (6, 3)
    eps = 1e-6
    base = fitted.predict(p0[None])["L"][0]
    num = np.stack([(fitted.predict((p0 + eps * e)[None])["L"][0] - base) / eps for e in np.eye(3)], axis=1)
    assert np.allclose(J, num, atol=1e-5)
    assert np.all(J[:, 2] == 0.0)


def test_noisy_fit_error_shrinks_with_samples() -> None:
    """Least squares on noisy data: prediction error ~ sigma * sqrt(3 p / n), far below the noise."""
    rng = np.random.default_rng(2)
    P = rng.uniform(-0.5, 0.5, (400, 3))
    lm = fit_linkmap(NAMES, [0, 0, 0], [0.5, 0.5, 0.5], P, observations(P, sigma=1e-4, seed=3))
    Q = rng.uniform(-0.5, 0.5, (200, 3))
    pred = lm.predict(Q)["L"][:, :3]
    err = np.linalg.norm(pred - np.array([truth(q)[0] for q in Q]), axis=1)
    p_feat = len(quad_features(np.zeros((1, len(lm.links["L"].actuators))))[0])
    bound = 1.5 * 1e-4 * np.sqrt(3 * p_feat / 400)
    assert np.sqrt(np.mean(err**2)) < bound


def test_save_load_round_trip(tmp_path: Path, fitted: LinkMap) -> None:
    path = fitted.save(tmp_path / "lm.json")
    again = LinkMap.load(path)
    assert again.actuators == fitted.actuators
    p = {"a": 0.2, "b": 0.1, "c": -0.3}
    assert np.allclose(again.poses(p)["L"], fitted.poses(p)["L"], atol=1e-12)
    doc = json.loads(path.read_text())
    assert doc["format"] == "likeness.linkmap" and doc["version"] == 1
    assert doc["links"]["L"]["samples"] == 80 and "residual" in doc["links"]["L"]
    assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves no temp file


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda d: d.update(version=99), "version"),
        (lambda d: d["links"]["L"].update(coefficients=[[0.0] * 6]), "links.L.coefficients"),
        (lambda d: d["links"]["L"].update(actuators=["zz"]), "links.L.actuators"),
        (lambda d: d.update(neutral=[0.0]), "neutral"),
    ],
)
def test_load_refuses_bad_files_naming_the_key(tmp_path: Path, fitted: LinkMap, edit, key: str) -> None:
    doc = fitted.to_dict()
    edit(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(SpecError, match=key.replace(".", r"\.")):
        LinkMap.load(path)


def _sample_map(head) -> LinkMap:
    """A trivially fitted map over the sample head's actuators and links (constant poses)."""
    names = head.actuator_names
    n = 40
    rng = np.random.default_rng(0)
    P = rng.uniform(-0.1, 0.1, (n, len(names)))
    obs = {
        link.name: LinkObservations(np.tile([0.0, 0.0, 0.1], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), np.ones(n, bool))
        for link in head.links
    }
    return fit_linkmap(names, np.zeros(len(names)), np.ones(len(names)), P, obs,
                       config_links={link.name: link.actuators for link in head.links},
                       rigid=[link.name for link in head.links if link.rigid])


def test_check_against_refuses_mismatch_by_name(tmp_path: Path) -> None:
    head = load_head(SAMPLE)
    lm = _sample_map(head)
    lm.check_against(head)  # matches
    path = lm.save(tmp_path / "lm.json")
    doc = json.loads(path.read_text())
    doc["actuators"][0] = "jaw_motor"
    for fit in doc["links"].values():
        fit["actuators"] = ["jaw_motor" if a == "jaw" else a for a in fit["actuators"]]
    path.write_text(json.dumps(doc))
    bad = LinkMap.load(path)
    with pytest.raises(SpecError, match="jaw") as err:
        bad.check_against(head)
    assert "lacks: jaw" in str(err.value)
    doc = lm.to_dict()
    doc["links"]["chin"] = doc["links"].pop("jaw")
    path.write_text(json.dumps(doc))
    with pytest.raises(SpecError, match="link map lacks: jaw"):
        LinkMap.load(path).check_against(head)


def test_actuators_that_always_move_together_keep_the_configured_one() -> None:
    """Lids in a "together" group move as one: the data cannot separate them, the head config decides."""
    rng = np.random.default_rng(4)
    P = rng.uniform(-0.5, 0.5, (80, 3))
    P[:, 1] = P[:, 0]  # a and b always equal
    lm = fit_linkmap(NAMES, [0, 0, 0], [0.5, 0.5, 0.5], P, observations(P), config_links={"L": ["b"]})
    assert lm.links["L"].actuators == ("b",)
    lm = fit_linkmap(NAMES, [0, 0, 0], [0.5, 0.5, 0.5], P, observations(P))
    assert lm.links["L"].actuators == ("a",)
    x = {"a": 0.2, "b": 0.2}
    assert np.allclose(lm.poses(x)["L"][:3, 3], truth(np.array([0.2, 0.2, 0.0]))[0], atol=1e-9)
