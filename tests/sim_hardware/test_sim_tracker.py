"""Simulated tracker: noise, dropouts, outliers at their rates; CSV export/replay; ZeroMQ frame format."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.capture import CSV_COLUMNS, CaptureLog, pack_frame, read_csv, unpack_frame, write_csv
from models.errors import SpecError
from models.rigid import quat_to_matrix, rotation_angle
from sim_hardware.mechanism import sample_mechanism
from sim_hardware.tracker import SimTracker, TrackerNoise


@pytest.fixture(scope="module")
def mech():
    return sample_mechanism(seed=5)


def test_noise_dropout_and_outlier_rates(mech) -> None:
    noise = TrackerNoise(position_sigma=0.2e-3, rotation_sigma=math.radians(0.2), dropout_rate=0.1, outlier_rate=0.05)
    tr = SimTracker(mech, lambda: {"jaw": 0.2}, noise=noise, seed=3)
    samples = tr.capture(400)
    truth = mech.link_poses({"jaw": 0.2})
    n_links = len(mech.links)
    assert abs(len(samples) / (400 * n_links) - 0.9) < 0.02
    err = np.array([np.linalg.norm(np.subtract(s.position, truth[s.link][:3, 3])) for s in samples])
    outliers = err > 5e-3
    assert abs(outliers.mean() - 0.05) < 0.015
    per_axis = np.sqrt(np.mean(err[~outliers] ** 2) / 3)
    assert per_axis == pytest.approx(0.2e-3, rel=0.1)
    ang = [rotation_angle(quat_to_matrix(np.array(s.quaternion)).T @ truth[s.link][:3, :3])
           for s, o in zip(samples, outliers, strict=True) if not o]
    assert np.sqrt(np.mean(np.square(ang)) / 3) == pytest.approx(math.radians(0.2), rel=0.1)
    times = sorted({s.time for s in samples})
    assert np.allclose(np.diff(times), 1 / 120, atol=2e-6)  # one frame per period


def test_csv_round_trip_and_windows(tmp_path: Path, mech) -> None:
    tr = SimTracker(mech, lambda: {}, seed=1)
    samples = tr.capture(5)
    path = write_csv(tmp_path / "cap.csv", samples)
    assert path.read_text().splitlines()[0] == ",".join(CSV_COLUMNS)
    back = read_csv(path)
    assert [s.link for s in back] == [s.link for s in samples]
    assert np.allclose([s.position for s in back], [s.position for s in samples], atol=1e-7)
    log = CaptureLog(back)
    t = sorted({s.time for s in samples})
    assert {s.time for s in log.between(t[1], t[2])} == {t[1], t[2]}


def test_csv_errors_name_row_and_column(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("time,link,x,y,z,qw,qx,qy,qz\n0.0,jaw,0,0,0,1,0,0,0\n0.1,jaw,0,zero,0,1,0,0,0\n")
    with pytest.raises(SpecError, match="row 3"):
        read_csv(bad)
    bad.write_text("t,link,x,y,z\n")
    with pytest.raises(SpecError, match="header"):
        read_csv(bad)


def test_stream_frame_round_trip(mech) -> None:
    tr = SimTracker(mech, lambda: {}, noise=TrackerNoise(dropout_rate=0.0), seed=2)
    samples = tr.capture(1)
    back = unpack_frame(pack_frame(7, samples))
    assert [s.link for s in back] == [s.link for s in samples]
    assert np.allclose([s.quaternion for s in back], [s.quaternion for s in samples])
    with pytest.raises(ValueError, match="two-part"):
        unpack_frame([b"other", b""])
