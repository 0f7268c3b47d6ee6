"""The exact FEM pose of a head as a worker process: ``python -m offline.pose_worker HEAD.toml``.

Tools that must not import offline code (the studio) run this module as a child process and speak one JSON object
per line: a request ``{"p": [actuator values, SI]}`` on stdin, a reply on stdout, ``{"ok": true, "surface":
[[x, y, z], ...] (outer-surface positions, m), "converged": bool, "iterations": int}`` or ``{"ok": false, "error":
message}``. The worker loads the head's FEM problem (``offline.dataset.fem_problem``: the skin mesh beside the head,
its link map and material) once, at the first request, and keeps it for later ones; the first solve also compiles
the FEM kernels (tens of seconds), later ones take seconds. It ends when stdin closes.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import IO, Any

import numpy as np


def mesh_folder(config: str | Path) -> Path:
    """The skin mesh of a head: ``[paths] skin_mesh`` when given, else ``skin/`` beside the head file."""
    from models.headspec import load_head

    head = load_head(config)
    given = head.path("skin_mesh")
    return Path(given) if given is not None else Path(head.source).parent / "skin"


class ExactPose:
    """The head's FEM problem, built on first use: :meth:`solve` gives the outer surface at a pose."""

    def __init__(self, config: str | Path) -> None:
        self.config = str(config)
        self._problem: Any = None

    def solve(self, p: list[float]) -> tuple[np.ndarray, bool, int]:
        """Outer-surface positions (V, 3) m of the FEM solution at actuator pose ``p`` (SI), converged, iterations."""
        if self._problem is None:
            from models.headspec import load_head
            from offline.dataset.fem_problem import FemSpec, material_fields

            head = load_head(self.config)
            linkmap = head.path("linkmap")
            if linkmap is None:
                raise ValueError(f"{self.config}: the exact FEM pose needs the head's link map ([paths] linkmap)")
            spec = FemSpec(config=str(head.source), mesh=str(mesh_folder(self.config)), linkmap=str(linkmap),
                           **material_fields(head.skin_material()))
            self._problem = spec.build()
        sol = self._problem.solve(np.asarray(p, dtype=np.float64), None)
        return np.asarray(sol.surface, dtype=np.float64), bool(sol.converged), int(sol.iterations)


def serve(config: str | Path, requests: IO[str], replies: IO[str]) -> None:
    """Answer each request line with one reply line until ``requests`` ends."""
    poser = ExactPose(config)
    for line in requests:
        if not line.strip():
            continue
        try:
            surface, converged, iterations = poser.solve([float(x) for x in json.loads(line)["p"]])
            reply: dict[str, Any] = {"ok": True, "surface": surface.tolist(), "converged": converged,
                                     "iterations": iterations}
        except Exception as exc:  # one bad pose or head is this request's error, not the worker's end
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        replies.write(json.dumps(reply) + "\n")
        replies.flush()


def main(argv: list[str] | None = None) -> int:
    """Serve exact poses of the head named on the command line over stdin/stdout."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m offline.pose_worker HEAD.toml", file=sys.stderr)
        return 2
    replies, sys.stdout = sys.stdout, sys.stderr  # anything the solver prints must not garble the replies
    serve(args[0], sys.stdin, replies)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
