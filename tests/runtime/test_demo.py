"""``likeness demo`` (what ``make demo`` runs) plays the bundled performance on emulated hardware and plots it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from runtime.recording import load_recording, tracking_errors
from tests.runtime.conftest import ROOT


def test_demo_plays_the_performance_and_writes_a_plot(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "likeness", "demo", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=120, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "100%" in out.stdout and "tracking error" in out.stdout and "missed deadlines" in out.stdout
    # Each performance says how fresh its buses' feedback stayed.
    assert "feedback of 'expressive': largest age can0 " in out.stdout and " dxl " in out.stdout
    png = tmp_path / "expressive.png"
    assert png.read_bytes()[:4] == b"\x89PNG"
    rec = load_recording(tmp_path / "expressive.lrec")
    assert len(rec["names"]) == 13 and rec["t"][-1] > 8.5
    errors = tracking_errors(rec)
    # Every actuator printed, and each followed its command (stepped lids lag most).
    for name, err in errors.items():
        assert name in out.stdout
        assert err["rms"] < 3.0, (name, err)
    # The blendshape performance is solved through the skin predictor and moves the motors too.
    assert "performance 'blendshapes'" in out.stdout
    shapes = load_recording(tmp_path / "blendshapes.lrec")
    assert (tmp_path / "blendshapes.png").read_bytes()[:4] == b"\x89PNG"
    moved = abs(shapes["measured"]).max(axis=0)  # config units (degrees)
    assert (moved > 0.5).sum() >= 5, dict(zip(shapes["names"], moved, strict=True))


def test_the_demo_counts_the_loops_missed_deadlines_by_their_recorded_cause() -> None:
    from runtime.demo import MissesSeen

    seen = MissesSeen()
    seen.take("state", {"loop": {"missed": 3}})  # the counter alone names no cause
    seen.take("event", {"event": "fault", "t": 1.0})
    seen.take("event", {"event": "deadline_miss", "count": 3, "causes": [
        {"cause": "not_scheduled", "missed": 2}, {"cause": "work_slow", "missed": 1}]})
    seen.take("event", {"event": "deadline_miss", "count": 1, "causes": [{"cause": "not_scheduled", "missed": 1}]})
    assert seen.by_cause == {"not_scheduled": 3, "work_slow": 1}
