"""The exact FEM pose, off the page's thread: a worker process solves the skin FEM for one actuator pose.

The worker is ``python -m offline.pose_worker HEAD.toml``, a child process speaking JSON lines over its stdin and
stdout (the protocol is in that module's docstring); the studio imports no offline code. The worker loads the head's
FEM problem once and keeps it for later poses; the first solve also compiles the FEM kernels (tens of seconds),
later ones take seconds.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

#: What a solve gives: outer-surface positions (V, 3) m, converged, Newton iterations.
ExactSolution = tuple[np.ndarray, bool, int]


class ExactPoser:
    """One worker process solving exact poses in turn (started at the first pose, ended by :meth:`close`)."""

    def __init__(self, config: str | Path) -> None:
        self.config = str(Path(config).resolve())
        self._proc: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()  # one request on the pipe at a time
        self._pool = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="exact-pose")

    def submit(self, p: np.ndarray) -> cf.Future[ExactSolution]:
        """The exact pose at actuator values ``p`` (SI), solved in the worker."""
        return self._pool.submit(self._solve, [float(x) for x in p])

    def _solve(self, p: list[float]) -> ExactSolution:
        with self._lock:
            if self._proc is None or self._proc.poll() is not None:
                self._proc = subprocess.Popen([sys.executable, "-m", "offline.pose_worker", self.config],
                                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            proc = self._proc
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.write(json.dumps({"p": p}) + "\n")
            proc.stdin.flush()
            line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the exact-pose worker ended (status {proc.poll()})")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise RuntimeError(f"exact pose failed: {reply.get('error')}")
        return np.asarray(reply["surface"], dtype=np.float64), bool(reply["converged"]), int(reply["iterations"])

    def close(self) -> None:
        """Stop the worker, ending a solve still running (the page is going away)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            proc.wait()
        self._pool.shutdown(wait=False, cancel_futures=True)
