"""The shared e-stop flag carries the latest trip's reason across processes, along with the trip itself; the
command pipe delivers messages whole, in order, without blocking the writer or long reads in the loop."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from runtime.ipc import EStopFlag, PipeReader, PipeWriter, make_pipe

ROOT = Path(__file__).resolve().parents[2]


def test_a_trip_in_another_process_is_seen_once_with_its_reason() -> None:
    flag = EStopFlag()
    try:
        assert not flag.tripped() and flag.reason() == "api"
        code = ("import sys; from runtime.ipc import EStopFlag; f = EStopFlag(sys.argv[1]); "
                "f.trip('studio E-stop'); f.close()")
        env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        subprocess.run([sys.executable, "-c", code, flag.name], check=True, timeout=60, env=env)
        assert flag.tripped() and flag.reason() == "studio E-stop"
        assert not flag.tripped()  # once per trip
        flag.trip("é" * 100)  # long, non-ASCII: cut to 63 bytes, a broken last character replaced, never an error
        assert flag.tripped() and flag.reason().startswith("é")
    finally:
        flag.close()


# ---------------------------------------------------------------------------------------------------- command pipe
def _pipe(tmp_path: Path) -> tuple[PipeReader, PipeWriter]:
    path = str(tmp_path / "commands")
    make_pipe(path)
    reader = PipeReader(path)  # the reader opens first, as the daemon does
    return reader, PipeWriter(path)


def _drain(reader: PipeReader, writer: PipeWriter, n: int) -> list:
    got: list = []
    for _ in range(100_000):
        if len(got) >= n:
            break
        writer.flush()
        got += reader.recv()
    return got


def test_pipe_messages_arrive_whole_and_in_order_small_and_large(tmp_path: Path) -> None:
    reader, writer = _pipe(tmp_path)
    try:
        big = np.random.default_rng(0).random(3_000_000)  # 24 MB: far more than the pipe holds
        sent = [("cmd", 1), ("cmd", {"a": np.arange(5)}), ("cmd", big), ("cmd", "after the big one"),
                ("cmd", [np.ones(70_000), np.zeros(2)])]
        for msg in sent:
            writer.send(msg)  # never blocks: what the pipe cannot take yet waits in order
        assert writer.wants_write and writer.queued_bytes > 0
        got = _drain(reader, writer, len(sent))
        assert [g[0] for g in got] == ["cmd"] * len(sent)
        assert got[0][1] == 1 and got[3][1] == "after the big one"
        np.testing.assert_array_equal(got[1][1]["a"], np.arange(5))
        np.testing.assert_array_equal(got[2][1], big)
        np.testing.assert_array_equal(got[4][1][0], np.ones(70_000))
        assert not writer.wants_write and writer.queued_bytes == 0
    finally:
        writer.close()
        reader.close()


def test_pipe_reads_are_bounded_per_call(tmp_path: Path) -> None:
    reader, writer = _pipe(tmp_path)
    try:
        writer.send(("cmd", np.zeros(200_000)))  # 1.6 MB
        calls = 0
        got: list = []
        while not got:
            writer.flush()
            got = reader.recv(max_bytes=64 * 1024)
            calls += 1
        assert calls >= 1_600_000 // (64 * 1024)  # the large message took many short reads, never one long one
        for i in range(100):
            writer.send(("cmd", i))
        firsts = reader.recv(max_messages=10)
        assert [m[1] for m in firsts] == list(range(10))
        assert [m[1] for m in _drain(reader, writer, 90)] == list(range(10, 100))
    finally:
        writer.close()
        reader.close()


def test_pipe_reader_sees_the_writer_go_and_the_writer_a_missing_reader(tmp_path: Path) -> None:
    reader, writer = _pipe(tmp_path)
    writer.send(("cmd", "last"))
    writer.close()
    assert [m[1] for m in reader.recv()] == ["last"]
    assert reader.recv() == [] and reader.closed  # end of file: the server is gone
    reader.close()
    (tmp_path / "again").mkdir()
    reader, writer = _pipe(tmp_path / "again")
    reader.close()  # the loop is gone
    with pytest.raises(BrokenPipeError):
        writer.send(("cmd", "nobody reads"))
    writer.close()


def test_a_live_value_crosses_the_pipe_whole_and_small(tmp_path: Path) -> None:
    """A show-control value (runtime.core.commands.Live) is pickled with its arrays as raw bytes: every field comes
    back equal, dtypes and shapes included."""
    from runtime.core.commands import Live

    sent = [Live(7, "sacn", np.array([3, 11, 12], dtype=np.intp), np.array([0.5, -1.25, 2.0]), at=4.5, received=4.25,
                 takeover=False, watchdog_s=0.5),
            Live(8, "osc", np.array([1], dtype=np.int32), np.array([3.0], dtype=np.float32)),
            Live(9)]
    reader, writer = _pipe(tmp_path)
    try:
        for cmd in sent:
            writer.send(cmd)
        got = _drain(reader, writer, len(sent))
    finally:
        writer.close()
        reader.close()
    for a, b in zip(sent, got, strict=True):
        assert (a.token, a.source, a.at, a.received, a.takeover, a.watchdog_s) == \
            (b.token, b.source, b.at, b.received, b.takeover, b.watchdog_s)
        for x, y in ((a.channels, b.channels), (a.values, b.values)):
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(x, y)
