"""``likeness calibrate`` end to end with ideal motors, its CSV replay, and its user errors."""

from __future__ import annotations

import json
from pathlib import Path

from likeness.cli import main

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
SMALL = ["--samples", "12", "--sweep-levels", "3", "--frames", "4", "--no-discover", "--no-progress"]


def test_calibrate_then_replay_the_capture(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    rc = main(["calibrate", "--config", str(SAMPLE), "--tracker", "sim", "--ideal-motors", "--out", str(out), *SMALL])
    assert rc == 0
    text = capsys.readouterr().out
    assert "hold-out RMS" in text and "lip_corner_l" in text
    report = json.loads((out / "report.json").read_text())
    assert report["provenance"]["driver"] == "ideal-motors"
    rc = main(["calibrate", "--config", str(SAMPLE), "--tracker", str(out / "capture.csv"), "--journal",
               str(out / "journal.jsonl"), "--out", str(tmp_path / "refit"), "--no-progress"])
    assert rc == 0
    again = json.loads((tmp_path / "refit" / "report.json").read_text())
    assert abs(again["holdout_rms_mm"] - report["holdout_rms_mm"]) < 1e-3


def test_user_errors_exit_2_with_a_message(tmp_path, capsys) -> None:
    base = ["calibrate", "--config", str(SAMPLE), "--out", str(tmp_path / "x"), "--no-progress"]
    assert main([*base, "--tracker", "webcam"]) == 2
    assert "--tracker must be sim" in capsys.readouterr().err
    assert main([*base, "--tracker", str(tmp_path / "missing.csv")]) == 2
    assert "capture file not found" in capsys.readouterr().err
    (tmp_path / "cap.csv").write_text("time,link,x,y,z,qw,qx,qy,qz\n")
    assert main([*base, "--tracker", str(tmp_path / "cap.csv")]) == 2
    assert "journal not found" in capsys.readouterr().err
    assert main([*base, "--tracker", "sim", "--ideal-motors", "--speed", "2"]) == 2
    assert main(["calibrate", "--config", str(tmp_path / "nope.toml"), "--tracker", "sim", "--out", "x"]) == 2
    assert "cannot read head spec" in capsys.readouterr().err
