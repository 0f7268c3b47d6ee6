"""Generate a pose dataset on an engine: sample, solve each pose warm-started from its nearest solved pose, store.

Each task solves one pose in a worker and writes ``poses/pose_NNNNNN.npz`` itself, returning the path. The
driver keeps the set of solved poses, hands every new task the state file of the nearest converged one (in
normalized actuator space), prints progress with rate and ETA, records failures in ``failures.json`` and
finally consolidates the memory-mapped arrays. Rerunning the same command resumes: existing pose files are kept.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from models.atomic import write_bytes
from offline.dataset.problem import ProblemSpec, problem_for
from offline.dataset.store import PoseRecord, PoseStore
from offline.engine import Engine


def solve_pose_task(spec: ProblemSpec, root: str, index: int, p: np.ndarray, warm_path: str | None) -> str:
    """Worker side: solve pose ``index`` warm-started from ``warm_path`` and write its file; returns the path."""
    problem = problem_for(spec)
    store = PoseStore(root)
    warm = None
    if warm_path is not None:
        try:
            with np.load(warm_path) as z:
                warm = z["state"] if "state" in z.files else None
        except (OSError, ValueError, KeyError):
            warm = None  # a missing or unreadable warm start only costs iterations
    t0 = time.perf_counter()
    sol = problem.solve(np.asarray(p, dtype=float), warm, index=index)
    rec = PoseRecord(index=index, p=np.asarray(p, dtype=float), surface=sol.surface, converged=sol.converged,
                     iterations=sol.iterations, state=sol.state, seconds=time.perf_counter() - t0,
                     message=sol.message)
    return str(store.write_pose(rec))


class Progress:
    """A one-line progress report (done/total, rate, ETA) refreshed at most every ``interval`` seconds."""

    def __init__(self, total: int, already: int, stream: TextIO | None = sys.stderr, interval: float = 1.0) -> None:
        self.total = total
        self.done = already
        self.start_done = already
        self.t0 = time.monotonic()
        self.last = 0.0
        self.stream = stream
        self.interval = interval
        self.failed = 0
        self.not_converged = 0

    def rate(self) -> float:
        dt = time.monotonic() - self.t0
        return (self.done - self.start_done) / dt if dt > 0 else 0.0

    def line(self) -> str:
        rate = self.rate()
        left = self.total - self.done
        eta = left / rate if rate > 0 else float("inf")
        eta_txt = "?" if not np.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        pct = 100.0 * self.done / max(self.total, 1)
        return (f"poses {self.done}/{self.total} ({pct:.0f} %)  {rate * 3600:.0f}/h  ETA {eta_txt}  "
                f"not converged {self.not_converged}  failed {self.failed}")

    def update(self, n: int = 1, force: bool = False) -> None:
        self.done += n
        now = time.monotonic()
        if self.stream is not None and (force or now - self.last >= self.interval):
            self.last = now
            self.stream.write("\r" + self.line())
            self.stream.flush()

    def finish(self) -> None:
        if self.stream is not None:
            self.stream.write("\r" + self.line() + "\n")
            self.stream.flush()


def generate_dataset(root: str | Path, spec: ProblemSpec, samples: np.ndarray, *, head: str,
                     names: Sequence[str], units: Sequence[str], lo: np.ndarray, hi: np.ndarray,
                     engine: Engine, seed: int, sampling: dict[str, Any],
                     progress_stream: TextIO | None = sys.stderr, max_in_flight: int | None = None,
                     max_poses: int | None = None, indices: Sequence[int] | None = None,
                     rest_pose: Sequence[float] | None = None, start: str = "nearest",
                     reuse: str | Path | None = None) -> dict[str, Any]:
    """Create (or resume) the dataset at ``root`` and solve every missing pose; returns a summary.

    ``start``: each solve starts from the nearest converged pose (``"nearest"``) or from rest (``"rest"``: labels
    that do not depend on the order poses finish in, for skins with several equilibria); recorded in the manifest
    as ``start`` (a dataset without it was made from the nearest pose), and a resume must use the same.

    ``rest_pose``: actuator values (SI) at which the problem's surface is exactly at rest (the head's neutral pose
    for the FEM skin, where the link map moves nothing); stored in the manifest so training can pin the predictor
    to zero offsets there.

    ``max_poses`` stops after that many newly solved poses (for tests and partial runs); ``indices`` restricts
    the run to those planned poses (active learning simulates the poses its policy chose, batch by batch).
    ``reuse``: a dataset of the same physics whose solved, converged poses at a planned pose's values are copied
    instead of solved (:mod:`offline.dataset.reuse`); the summary counts them as ``reused``.
    """
    root = Path(root)
    store = PoseStore(root)
    problem = problem_for(spec)
    fu_names, fu_offsets = problem.face_units()
    manifest = {
        "head": head,
        "actuators": [{"name": n, "unit": u, "min": float(a), "max": float(b)}
                      for n, u, a, b in zip(names, units, lo, hi, strict=True)],
        "n_poses": len(samples), "seed": int(seed), "sampling": sampling, "problem": spec.describe(),
        "n_vertices": int(problem.base_surface().shape[0]), "mesh": problem.mesh_info(),
    }
    if start not in ("nearest", "rest"):
        raise ValueError(f"start must be 'nearest' or 'rest', got {start!r}")
    manifest["start"] = start
    if rest_pose is not None:
        rest = [float(x) for x in rest_pose]
        if len(rest) != len(names) or not all(np.isfinite(rest)):
            raise ValueError(f"rest_pose: expected {len(names)} finite actuator values, got {rest_pose!r}")
        manifest["rest_pose"] = rest
    store.create(manifest, samples, problem.base_surface(), problem.faces(), fu_names, fu_offsets,
                 regions=problem.surface_regions())
    samples = store.samples()  # on resume, the stored plan wins
    store.remove_leftovers()  # temp files of a killed run
    xs = (samples - np.asarray(lo)) / (np.asarray(hi) - np.asarray(lo))
    done = store.done()
    wanted = range(len(samples)) if indices is None else sorted({int(i) for i in indices})
    reused: list[int] = []
    if reuse is not None:
        from offline.dataset.reuse import reuse_solved

        reused = reuse_solved(store, reuse, [i for i in wanted if i not in done])
        done = store.done()
    solved_idx: list[int] = []
    for i in sorted(done):
        if store.read_pose(i).converged:
            solved_idx.append(i)
    todo = [i for i in wanted if i not in done]
    if max_poses is not None:
        todo = todo[:max_poses]
    failures_path = root / "failures.json"
    failures: dict[str, str] = json.loads(failures_path.read_text()) if failures_path.exists() else {}
    total = len(samples) if indices is None else len(done) + len(todo)
    prog = Progress(total, len(done), progress_stream)
    t0 = time.perf_counter()

    def make_args(i: int) -> tuple[Any, ...]:
        warm = None
        if solved_idx and start == "nearest":
            cand = np.asarray(solved_idx)
            j = int(cand[np.argmin(((xs[cand] - xs[i]) ** 2).sum(axis=1))])
            warm = str(store.pose_path(j))
        return (spec, str(root), i, samples[i], warm)

    new = 0
    for out in engine.run(solve_pose_task, todo, make_args, max_in_flight=max_in_flight):
        i = int(out.key)
        if out.ok:
            failures.pop(str(i), None)
            if store.read_pose(i).converged:
                solved_idx.append(i)
            else:
                prog.not_converged += 1
            new += 1
        else:
            failures[str(i)] = out.error or "unknown error"
            prog.failed += 1
            write_bytes(failures_path, json.dumps(failures, indent=1).encode())
        prog.update()
    prog.finish()
    if failures:
        write_bytes(failures_path, json.dumps(failures, indent=1).encode())
    elif failures_path.exists():
        failures_path.unlink()
    complete = len(store.done()) == len(samples)
    if complete:
        store.consolidate()
    dt = time.perf_counter() - t0
    return {"root": str(root), "poses": len(samples), "solved_now": new, "reused": len(reused),
            "done": len(store.done()),
            "failed": len(failures), "not_converged": prog.not_converged, "seconds": dt,
            "poses_per_hour": new / dt * 3600 if dt > 0 else 0.0, "complete": complete}
