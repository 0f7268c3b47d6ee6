"""The exact FEM pose, off the page's thread: a worker process solves the skin FEM for one actuator pose.

The worker loads the head's FEM problem (``offline.dataset.fem_problem``: the skin mesh beside the head, its link
map and material) once and keeps it for later poses; the first solve also compiles the FEM kernels (tens of
seconds), later ones take seconds. Offline code is imported only inside the worker process.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
from pathlib import Path

import numpy as np

_PROBLEM: dict[str, object] = {}


def mesh_folder(config: str | Path) -> Path:
    """The skin mesh of a head: ``[paths] skin_mesh`` when given, else ``skin/`` beside the head file."""
    from models.headspec import load_head

    head = load_head(config)
    given = head.path("skin_mesh")
    return Path(given) if given is not None else Path(head.source).parent / "skin"


def solve_exact(config: str, p: list[float]) -> tuple[np.ndarray, bool, int]:
    """Outer-surface positions (V, 3) m of the FEM solution at actuator pose ``p`` (SI), converged, iterations.

    Runs in the worker process.
    """
    from models.headspec import load_head
    from offline.dataset.fem_problem import FemSpec, material_fields

    prob = _PROBLEM.get(config)
    if prob is None:
        head = load_head(config)
        linkmap = head.path("linkmap")
        if linkmap is None:
            raise ValueError(f"{config}: the exact FEM pose needs the head's link map ([paths] linkmap)")
        spec = FemSpec(config=str(head.source), mesh=str(mesh_folder(config)), linkmap=str(linkmap),
                       **material_fields(head.skin_material()))
        prob = spec.build()
        _PROBLEM[config] = prob
    sol = prob.solve(np.asarray(p, dtype=np.float64), None)  # type: ignore[attr-defined]
    return np.asarray(sol.surface, dtype=np.float64), bool(sol.converged), int(sol.iterations)


class ExactPoser:
    """One worker process (spawned, so it shares nothing with the page's threads) solving exact poses in turn."""

    def __init__(self, config: str | Path) -> None:
        self.config = str(Path(config).resolve())
        self._pool: cf.ProcessPoolExecutor | None = None

    def submit(self, p: np.ndarray) -> cf.Future:
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool.submit(solve_exact, self.config, [float(x) for x in p])

    def close(self) -> None:
        """Stop the worker, ending a solve still running (the page is going away)."""
        if self._pool is not None:
            procs = list(getattr(self._pool, "_processes", {}).values())
            self._pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
            self._pool = None
