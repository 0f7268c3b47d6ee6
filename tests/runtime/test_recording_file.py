"""The streamed recording file: append-only, readable up to the last complete row after a cut or a SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from runtime.recording import RecordingWriter, load_recording, read_lrec_header, tracking_errors

ROOT = Path(__file__).resolve().parents[2]
NAMES, UNITS = ["jaw", "brow_l"], ["deg", "mm"]


def _rows(n: int, t0: float = 100.0) -> np.ndarray:
    t = t0 + 0.002 * np.arange(n)
    return np.column_stack([t, np.sin(t), t * 2, np.sin(t) + 0.1, t * 2 - 0.5])


def test_rows_round_trip_with_time_from_the_first_row(tmp_path: Path) -> None:
    rows = _rows(250)
    with RecordingWriter(tmp_path / "a.lrec", NAMES, UNITS, {"head": "sample"}) as w:
        w.append(rows[:1][0])  # one row as a vector
        w.append(rows[1:100])
        w.append(rows[100:])
    rec = load_recording(tmp_path / "a.lrec")
    assert rec["names"] == NAMES and rec["units"] == UNITS and rec["meta"]["head"] == "sample"
    np.testing.assert_array_equal(rec["t"], rows[:, 0] - rows[0, 0])
    np.testing.assert_array_equal(rec["commanded"], rows[:, 1:3])
    np.testing.assert_array_equal(rec["measured"], rows[:, 3:5])
    errors = tracking_errors(rec)
    assert errors["jaw"]["rms"] == pytest.approx(0.1) and errors["brow_l"]["max"] == pytest.approx(0.5)


def test_a_file_cut_at_any_byte_reads_its_complete_rows(tmp_path: Path) -> None:
    path = tmp_path / "cut.lrec"
    rows = _rows(40)
    with RecordingWriter(path, NAMES, UNITS) as w:
        w.append(rows)
    data = path.read_bytes()
    _, start = read_lrec_header(path)
    assert start % 8 == 0 and len(data) == start + rows.size * 8
    rng = np.random.default_rng(7)
    cuts = sorted({start, len(data), *rng.integers(start, len(data), 60).tolist()})
    for cut in cuts:
        short = tmp_path / "short.lrec"
        short.write_bytes(data[:cut])
        rec = load_recording(short)
        n = (cut - start) // (rows.shape[1] * 8)
        assert len(rec["t"]) == n, cut
        np.testing.assert_array_equal(rec["commanded"], rows[:n, 1:3])
        assert rec["meta"]["partial_bytes"] == (cut - start) % (rows.shape[1] * 8)


def test_a_cut_inside_the_header_and_other_files_are_named_errors(tmp_path: Path) -> None:
    path = tmp_path / "h.lrec"
    RecordingWriter(path, NAMES, UNITS).close()
    path.write_bytes(path.read_bytes()[:20])
    with pytest.raises(ValueError, match=r"h\.lrec: incomplete recording header"):
        load_recording(path)
    bad = tmp_path / "bad.lrec"
    bad.write_bytes(b'{"format": "other"}\n')
    with pytest.raises(ValueError, match="not a recording file"):
        load_recording(bad)
    binary = tmp_path / "bin.npz"
    binary.write_bytes(b"\x00\xff" * 50)
    with pytest.raises(ValueError, match=r"bin\.npz: not a recording file"):
        load_recording(binary)


def test_wrong_width_is_refused_and_existing_files_are_not_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "w.lrec"
    with RecordingWriter(path, NAMES, UNITS) as w, pytest.raises(ValueError, match="5 columns"):
        w.append(np.zeros((3, 4)))
    with pytest.raises(FileExistsError):
        RecordingWriter(path, NAMES, UNITS)


WRITER = """
import sys, time
import numpy as np
from runtime.recording import RecordingWriter
w = RecordingWriter(sys.argv[1], ["a", "b"], ["deg", "deg"], sync_s=1.0)
k = 0
while True:
    now = time.time()
    w.append(np.array([[now, k, k, now, now]]))
    k += 1
    if k == 5:
        print("ready", flush=True)
    time.sleep(0.01)
"""


def test_rows_older_than_a_second_survive_sigkill_of_the_writer(tmp_path: Path) -> None:
    path = tmp_path / "killed.lrec"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, env=env, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(1.6)
    finally:
        killed_at = time.time()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    rec = load_recording(path)
    wall = rec["measured"][:, 1]  # the wall-clock time each row was appended
    assert len(wall) > 20
    np.testing.assert_array_equal(rec["commanded"][:, 0], np.arange(len(wall)))  # no row lost in between
    assert wall[-1] >= killed_at - 1.0


def test_npz_recordings_still_load(tmp_path: Path) -> None:
    from runtime.recording import Recorder

    r = Recorder(NAMES, UNITS, [1.0, 1.0], 10)
    for k in range(5):
        r.add(10.0 + k, np.array([k, k]), np.array([k, k + 1.0]))
    rec = load_recording(r.save(tmp_path / "old.npz"))
    assert len(rec["t"]) == 5 and rec["names"] == NAMES


def test_summary_reads_frames_and_span_of_a_cut_file(tmp_path: Path) -> None:
    from runtime.recording import recording_summary

    path = tmp_path / "s.lrec"
    with RecordingWriter(path, NAMES, UNITS) as w:
        w.append(_rows(30))
    path.write_bytes(path.read_bytes()[:-13])
    frames, span = recording_summary(path)
    assert frames == 29 and span == pytest.approx(0.002 * 28)
    RecordingWriter(tmp_path / "empty.lrec", NAMES, UNITS).close()
    assert recording_summary(tmp_path / "empty.lrec") == (0, 0.0)
