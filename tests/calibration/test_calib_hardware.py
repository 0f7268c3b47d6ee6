"""Calibration through the emulated sample head's buses (CiA 402 drives and Dynamixel servos), driven by a daemon
of the bare mechanism (no skin predictor, as ``likeness calibrate`` runs it).

The emulated motors move the virtual mechanism, and the simulated tracker sees the links where the mechanism
puts them for the motors' true positions; so each recorded link pose must agree with the mechanism evaluated
at the encoder readings the calibration recorded. Few poses by default (the emulated motors move at real
speed); the larger run with the accuracy bound is ``slow``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.linkmap import LinkMap
from offline.calibration.capture import CalibrationError
from offline.calibration.heads import DaemonHead
from offline.calibration.journal import Journal
from offline.calibration.workflow import CalibrationSettings, calibrate_live
from sim_hardware.tracker import SimTracker
from tests.calibration.conftest import SimSource, start_bare_daemon

DEG = math.pi / 180


def _run(head, mech, out, attempts: int = 3, **kw):
    """Calibrate on fresh emulated buses; if the emulated buses fault (they time out when the shared CPU is
    saturated), start them again and resume from the journal, as an operator would."""
    from drivers.errors import BusError

    s = CalibrationSettings(**{"samples": 4, "sweep_levels": 2, "frames_per_pose": 4, "discover": False,
                               "progress": False, "tie_groups": True, **kw})  # the daemon moves "together" groups
    for attempt in range(attempts):
        daemon = start_bare_daemon(head, out)
        driver = None
        try:
            driver = DaemonHead(daemon.command_endpoint, head, speed_fraction=1.0)
            src = SimSource(SimTracker(mech, daemon.hw.simulated_positions, seed=11 + attempt))
            return calibrate_live(head, driver, src, out, s, reference=mech.rest_poses())
        except (CalibrationError, BusError):
            if attempt == attempts - 1:
                raise
        finally:
            if driver is not None:
                driver.close()
            daemon.stop()
    raise AssertionError("unreachable")


def test_calibration_drives_the_emulated_motors_and_the_tracker_sees_the_mechanism(
    tmp_path, sample_head, sample_mech
) -> None:
    res = _run(sample_head, sample_mech, tmp_path)
    journal = Journal(tmp_path / "journal.jsonl").load()
    assert len(journal.poses) == res.linkmap.provenance["poses"] > 15
    moved = 0
    for rec in journal.poses.values():
        for name, value in rec["commanded"].items():
            assert rec["measured"][name] == pytest.approx(value, abs=0.5 * DEG), name  # settled on target
        truth = sample_mech.link_poses(rec["measured"])
        for link, est in rec["links"].items():
            assert np.linalg.norm(np.subtract(est["p"], truth[link][:3, 3])) < 0.6e-3, link
        moved += abs(rec["measured"]["jaw"]) > 5 * DEG
    assert moved >= 2  # the jaw really went somewhere
    lm = LinkMap.load(tmp_path / "linkmap.json")
    lm.check_against(sample_head)
    assert lm.links["jaw"].residual["rms_mm"] < 0.3


@pytest.mark.slow
def test_hardware_calibration_reaches_the_noise_floor(tmp_path, sample_head, sample_mech) -> None:
    from tests.calibration.test_calib_workflow import bound_mm, truth_errors_mm

    res = _run(sample_head, sample_mech, tmp_path, samples=60, sweep_levels=3, frames_per_pose=8)
    lm = res.linkmap
    derived, s1 = bound_mm(lm, 0.2e-3, 8 * 0.98, lm.provenance["fit_poses"])
    rms = float(np.sqrt(np.mean(truth_errors_mm(sample_head, sample_mech, lm) ** 2)))
    assert rms <= min(derived, s1)
    assert res.report["holdout_rms_mm"] <= 1.5 * res.report["noise_floor_mm"]


def test_limit_discovery_on_the_emulated_drives(tmp_path, sample_head) -> None:
    """The operator configured the jaw 12 degrees too wide: the slow sweep on the real drive emulators stops
    where the tracker shows the jaw no longer moving, and proposes a limit just inside the hard stop."""
    import tomllib
    from pathlib import Path

    from models.headspec import head_from_dict
    from offline.calibration.capture import estimate
    from offline.calibration.discovery import discover_limits
    from sim_hardware.mechanism import sample_mechanism

    data = tomllib.loads(Path(sample_head.source).read_text())
    for act in data["actuators"]:
        if act["name"] == "jaw":
            act["max"] = 40.0
    wide = head_from_dict(data, source=sample_head.source)
    mech = sample_mechanism(None, seed=5)  # hard stops from the real sample limits
    for attempt in range(3):  # emulated buses may fault before the first move on a saturated CPU: start again
        daemon = start_bare_daemon(wide, tmp_path, dict(data))
        try:
            driver = DaemonHead(daemon.command_endpoint, wide, speed_fraction=0.3)
            break
        except BaseException:
            daemon.stop()
            if attempt == 2:
                raise
    try:
        src = SimSource(SimTracker(mech, daemon.hw.simulated_positions, seed=13))

        def observe():
            return {n: e.position for n, e in estimate(src.collect(4), list(mech.links), 4).items()}

        res = discover_limits(wide, driver, observe, actuators=["jaw"], step=2 * DEG)
    finally:
        driver.close()
        daemon.stop()
    stop = mech.stops["jaw"][1] + mech.zero_error["jaw"]
    assert res["jaw"].stop_found == (False, True)
    assert res["jaw"].proposed[1] == pytest.approx(stop - 1 * DEG, abs=2.5 * DEG)
