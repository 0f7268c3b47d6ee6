"""The child processes a calibration runs: the head's daemon and the simulated marker tracker.

Calibration never opens buses or emulators itself: it starts ``likeness daemon`` for the head config (which starts
the bus emulators when the config says ``simulated = true``) and drives it through the protocol, and it reads the
simulated tracker (``likeness sim tracker``) over its ZeroMQ capture stream like any capture system. Each child
binds a free loopback port and announces its endpoint on its first line of output; its log goes to a file in the
run directory.

The daemon runs the bare mechanism (:func:`mechanism_config`): the head's config without its skin predictor, so the
skin-strain guard does not stop calibration poses short. The link map is measured on the mechanism, before and for
the skin's predictor, over the actuators' whole configured travel (the sample skin's guard, for one, holds the jaw
below about 10 of its 28 degrees).
"""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

from offline.calibration.capture import CalibrationError


class ChildProcess:
    """A ``likeness`` command as a child process: stdout lines come through a queue, stderr goes to ``log``."""

    def __init__(self, args: Sequence[str], log: Path, name: str, stdin: bool = False) -> None:
        self.name = name
        self.log = log
        log.parent.mkdir(parents=True, exist_ok=True)
        self._log = log.open("ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "likeness", *args], stdout=subprocess.PIPE, stderr=self._log,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, text=True, bufsize=1,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, args=(self.proc.stdout,), daemon=True)
        self._reader.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def expect(self, pattern: str, timeout_s: float) -> re.Match[str]:
        """The first output line that matches ``pattern`` (other lines are skipped); CalibrationError naming the
        child and the end of its log if it exits or stays silent for ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self.lines.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                raise CalibrationError(f"{self.name} did not answer within {timeout_s:g} s{self._log_tail()}") from None
            if line is None:
                self.proc.wait()
                raise CalibrationError(f"{self.name} exited with status {self.proc.returncode}{self._log_tail()}")
            m = re.search(pattern, line)
            if m is not None:
                return m

    def _log_tail(self) -> str:
        self._log.flush()
        lines = self.log.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        return f": {lines[-1]} (log: {self.log})" if lines else f" (log: {self.log})"

    def close(self, timeout_s: float = 10.0) -> None:
        """SIGINT (the commands stop cleanly on it), then kill if it does not exit within ``timeout_s``."""
        if self.proc.poll() is None:
            if self.proc.stdin is not None:
                self.proc.stdin.close()
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


#: A relative file reference of a head config (``key = "file.ext"``), made absolute in a derived config.
_FILE_REF = re.compile(r'^(\s*\w+\s*=\s*")([^"/][^"]*\.(?:onnx|json|npz|toml|csv))(")')
#: ``[paths]`` keys of the skin predictor and its strain guard, left out of the bare mechanism's config.
_SKIN_KEYS = re.compile(r"^\s*(predictor|predictor_optional|skin_guard)\s*=")


def mechanism_config(config: Path, out: Path) -> Path:
    """Write ``out``: the head config ``config`` without its skin predictor (so without the daemon's skin-strain
    guard), its other relative file references made absolute so the file may live anywhere."""
    config = Path(config).resolve()
    lines = []
    table = ""
    for line in config.read_text(encoding="utf-8").splitlines():
        header = re.match(r"^\s*\[+([^\]]+)\]+", line)
        if header is not None:
            table = header.group(1).strip()
        elif table == "paths" and _SKIN_KEYS.match(line):
            continue
        m = _FILE_REF.match(line)
        if m is not None and (config.parent / m.group(2)).exists():
            line = f"{m.group(1)}{(config.parent / m.group(2)).as_posix()}{m.group(3)}{line[m.end():]}"
        lines.append(line)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"# {config} without its skin predictor (written by likeness calibrate)\n" + "\n".join(lines)
                   + "\n", encoding="utf-8")
    return out


def start_daemon(config: Path, run_dir: Path, timeout_s: float = 60.0) -> tuple[ChildProcess, str]:
    """``likeness daemon`` for the bare mechanism of ``config`` (:func:`mechanism_config`) on free loopback ports;
    returns it and its command endpoint."""
    bare = mechanism_config(config, run_dir / "daemon_head.toml")
    child = ChildProcess(["daemon", "--config", str(bare), "--command", "tcp://127.0.0.1:*",
                          "--telemetry", "tcp://127.0.0.1:*"], run_dir / "daemon.log", "the head's daemon")
    try:
        endpoint = child.expect(r"^ready: .* commands (\S+),", timeout_s).group(1)
    except BaseException:
        child.close()
        raise
    return child, endpoint


class SimTrackerProcess:
    """``likeness sim tracker`` for the sample head: follows a daemon's measured positions, or (``daemon=None``)
    the positions :meth:`show` writes to it; ``endpoint`` is its ZeroMQ capture stream."""

    def __init__(self, config: Path, run_dir: Path, daemon: str | None, seed: int, noise_mm: float,
                 noise_deg: float, dropout: float, outliers: float, timeout_s: float = 30.0) -> None:
        follow = ["--daemon", daemon] if daemon is not None else ["--stdin"]
        args = ["sim", "tracker", "--config", str(config), *follow, "--bind", "tcp://127.0.0.1:*",
                "--seed", str(seed), "--noise-mm", repr(noise_mm), "--noise-deg", repr(noise_deg),
                "--dropout", repr(dropout), "--outliers", repr(outliers)]
        self.timeout_s = timeout_s
        self.child = ChildProcess(args, run_dir / "tracker.log", "the simulated tracker", stdin=daemon is None)
        try:
            self.endpoint = self.child.expect(r"^tracker: publishing .* on (\S+) ", timeout_s).group(1)
        except BaseException:
            self.child.close()
            raise

    def show(self, positions: Mapping[str, float]) -> None:
        """Move the tracked mechanism to ``positions`` (SI); returns once every frame published shows them."""
        stdin = self.child.proc.stdin
        if stdin is None:
            raise CalibrationError("the simulated tracker follows a daemon, not positions written to it")
        try:
            stdin.write(json.dumps(dict(positions)) + "\n")
            stdin.flush()
        except OSError as exc:
            raise CalibrationError(f"the simulated tracker is gone ({exc}; log: {self.child.log})") from exc
        self.child.expect(r"^ok$", self.timeout_s)

    def close(self) -> None:
        self.child.close()
