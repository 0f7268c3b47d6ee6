"""A corrupt file the daemon reads stops ``likeness daemon`` at start: one line naming the file, exit status 2, no
traceback, before any process or emulator starts. The same for a clip given to ``likeness stream``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample"
GARBAGE = bytes(range(256)) * 8  # not UTF-8, not JSON, not protobuf, not a zip


def _head_copy(tmp: Path) -> Path:
    """The sample head in ``tmp``: small files copied, the rest linked (a test replaces a link before it writes)."""
    head = tmp / "sample"
    head.mkdir()
    for item in SAMPLE.iterdir():
        dest = head / item.name
        if item.is_file() and item.stat().st_size < 2_000_000:
            shutil.copyfile(item, dest)
        else:
            dest.symlink_to(item)
    return head


def _likeness(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "likeness", *argv], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=120)


@pytest.mark.parametrize("asset, content", [
    ("head.toml", GARBAGE),
    ("head.toml", b"[head\nname = "),
    ("linkmap.json", GARBAGE),
    ("linkmap.json", b'{"links": {'),
    ("predictor.onnx", GARBAGE),
    ("skin_guard.npz", GARBAGE),
])
def test_a_corrupt_asset_stops_the_daemon_at_start_with_one_line(tmp_path: Path, asset: str, content: bytes) -> None:
    head = _head_copy(tmp_path)
    (head / asset).unlink()  # a large asset is a link to the sample head's own file: never write through it
    (head / asset).write_bytes(content)
    res = _likeness("daemon", "--config", str(head / "head.toml"), cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("likeness daemon: error: "), res.stderr[-3000:]
    assert asset in lines[0] and "Traceback" not in res.stderr


def test_a_corrupt_clip_stops_stream_with_one_line(tmp_path: Path) -> None:
    clip = tmp_path / "clip.json"
    clip.write_bytes(GARBAGE)
    res = _likeness("stream", str(clip), "--endpoint", "tcp://127.0.0.1:1", "--timeout", "0.2", cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert len(lines) == 1 and "clip.json" in lines[0] and "Traceback" not in res.stderr


def test_a_predictor_onnxruntime_refuses_stops_the_daemon_at_start(tmp_path: Path) -> None:
    """A predictor whose graph parses (names, metadata and weights read as usual) but names an operator onnxruntime
    does not know: the daemon's own processes never open it with onnxruntime, so its start-up check does."""
    head = _head_copy(tmp_path)
    onnx = (SAMPLE / "predictor.onnx").read_bytes()
    assert onnx.count(b"Tanh") == 3  # the hidden layer of each axis: one byte changed keeps the protobuf valid
    (head / "predictor.onnx").unlink()
    (head / "predictor.onnx").write_bytes(onnx.replace(b"Tanh", b"Tanx"))
    from models.predictor import SkinPredictor

    assert SkinPredictor(head / "predictor.onnx", session=False).weights.hidden > 0  # parses, as the loop reads it
    res = _likeness("daemon", "--config", str(head / "head.toml"), cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("likeness daemon: error: "), res.stderr[-3000:]
    assert "predictor.onnx" in lines[0] and "onnxruntime" in lines[0] and "Traceback" not in res.stderr
    print("\n" + lines[0][:300])
