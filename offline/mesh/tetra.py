"""Tetrahedralize the closed skin shell with fTetWild (pytetwild) and check the result.

pytetwild writes ``__tracked_surface.stl`` into the current directory, so it runs inside a temporary directory;
``vtk_ordering=True`` gives positively oriented tets, which is checked (and unused nodes dropped) afterwards.
"""

from __future__ import annotations

import contextlib
import tempfile
from dataclasses import dataclass

import numpy as np


class TetrahedralizeError(RuntimeError):
    """fTetWild failed or returned inverted/degenerate tets."""


@dataclass(frozen=True)
class TetParams:
    """fTetWild settings: target edge length (m), envelope as a fraction of the bounding-box diagonal,
    whether to coarsen, and the optimization iteration cap."""

    edge_length: float = 0.0035
    epsilon: float = 1e-3
    coarsen: bool = False
    num_opt_iter: int = 80


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each linear tet (positive = right-handed corner order)."""
    p = nodes[tets[:, :4]]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def tetrahedralize(vertices: np.ndarray, triangles: np.ndarray, params: TetParams,
                   threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Tet mesh (nodes (N, 3), tets (M, 4) int64, all positively oriented) filling the closed surface."""
    import pytetwild
    import pyvista  # noqa: F401  (pytetwild imports it at import time)

    with tempfile.TemporaryDirectory(prefix="likeness-tetwild-") as tmp, contextlib.chdir(tmp):
        nodes, tets = pytetwild.tetrahedralize(
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(triangles, dtype=np.int32),
            edge_length_abs=params.edge_length,
            epsilon=params.epsilon,
            coarsen=params.coarsen,
            num_opt_iter=params.num_opt_iter,
            num_threads=threads,
            vtk_ordering=True,
            quiet=True,
        )
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if len(tets) == 0:
        raise TetrahedralizeError("fTetWild returned no tetrahedra")
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    nodes, tets = nodes[used], remap[tets]
    vol = signed_volumes(nodes, tets)
    if (vol <= 0).any():
        raise TetrahedralizeError(f"{int((vol <= 0).sum())} of {len(tets)} tets are inverted or flat "
                                  f"(min signed volume {vol.min():.3e} m^3)")
    return nodes, tets
