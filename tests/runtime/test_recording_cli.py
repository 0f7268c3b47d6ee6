"""``likeness recording list|info|replay`` on streamed (.lrec) and older (.npz) recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from likeness.cli import main
from models.client import Client
from runtime.recording import Recorder, RecordingWriter, load_recording, replay_clip


def _write(path: Path, n: int = 101) -> None:
    t = np.linspace(0.0, 1.0, n)
    jaw = 10.0 * t
    with RecordingWriter(path, ["jaw", "blink"], ["deg", "deg"], {"head": "sample"}) as w:
        w.append(np.column_stack([t + 50.0, jaw, np.zeros(n), jaw - 0.2, np.zeros(n)]))


def test_list_and_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write(tmp_path / "take1.lrec")
    r = Recorder(["jaw"], ["deg"], [1.0], 4)
    for k in range(3):
        r.add(k * 0.5, np.array([1.0]), np.array([1.0]))
    r.save(tmp_path / "old.npz")
    (tmp_path / "broken.lrec").write_bytes(b"\x00\x01")
    assert main(["recording", "list", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "take1.lrec" in out and " 101 " in out and "1.000" in out
    assert "old.npz" in out and "broken.lrec" in out and "unreadable" in out
    assert main(["recording", "info", str(tmp_path / "take1.lrec")]) == 0
    out = capsys.readouterr().out
    assert "frames:   101" in out and "span:     1.000 s" in out and "jaw [deg]" in out and "head=sample" in out


def test_info_of_a_bad_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.lrec"
    bad.write_bytes(b"{not json\n")
    assert main(["recording", "info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("likeness recording: error: ") and "x.lrec" in err and err.count("\n") == 1


def test_replay_clip_is_decimated_within_the_key_budget(tmp_path: Path) -> None:
    _write(tmp_path / "r.lrec", n=5001)
    clip = replay_clip(load_recording(tmp_path / "r.lrec"), "replay-r", max_keys=400)
    keys = clip["channels"]["jaw"]["keys"]
    assert len(keys) <= 201 and keys[0] == [0.0, 0.0] and keys[-1] == pytest.approx([1.0, 10.0])


def test_replay_plays_the_commanded_curves_on_a_daemon(shared_daemon, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    _write(tmp_path / "take.lrec")
    with Client(shared_daemon.command_endpoint, timeout=30) as c:
        if c.call("status")["lifecycle"] == "fault":  # an emulated bus may time out on a loaded host
            c.call("reset")
    assert main(["recording", "replay", str(tmp_path / "take.lrec"), "--endpoint", shared_daemon.command_endpoint,
                 "--enable"]) == 0
    assert "replaying 'replay-take'" in capsys.readouterr().out
    with Client(shared_daemon.command_endpoint, timeout=30) as c:
        st = c.call("status")
        assert "replay-take" in str(st["timeline"])
        c.call("disable")
