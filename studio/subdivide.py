"""Loop subdivision of a triangle surface as a sparse matrix, so a smooth fine surface follows a coarse one per frame.

The studio shows the simulated skin surface as a face rather than as simulation triangles: the fine surface's
vertices are fixed linear combinations of the simulated surface's vertices (Loop's rules, all weights >= 0, each row
summing to 1), computed once; every frame is then one sparse matrix product. Boundary edges (the open rim of the
face, the lips) and edges shared by more than two triangles are kept as creases (cubic B-spline rule along them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Subdivision:
    """``matrix`` (fine vertices × coarse vertices, CSR) and the fine surface's triangles."""

    matrix: sp.csr_matrix
    faces: np.ndarray  # (F, 3) uint32, oriented as the coarse triangles

    @property
    def n_vertices(self) -> int:
        return int(self.matrix.shape[0])


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique edges (E, 2) with a < b, each triangle side's edge id (F, 3: sides ab, bc, ca) and triangles per edge."""
    sides = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
    edges, inverse = np.unique(np.sort(sides, axis=1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    return edges, inverse.reshape(-1, 3), np.bincount(inverse, minlength=len(edges))


def loop_step(faces: np.ndarray, n_vertices: int) -> Subdivision:
    """One Loop subdivision of a triangle surface with ``n_vertices`` vertices: the matrix (n + E, n) and triangles."""
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"faces must be a non-empty (F, 3) array, got shape {faces.shape}")
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise ValueError(f"faces index vertices outside 0..{n_vertices - 1}")
    n = n_vertices
    edges, side_edge, per_edge = _edges(faces)
    n_e = len(edges)
    crease = per_edge != 2
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def add(r: np.ndarray, c: np.ndarray, w: np.ndarray | float) -> None:
        rows.append(np.asarray(r, dtype=np.int64))
        cols.append(np.asarray(c, dtype=np.int64))
        vals.append(np.broadcast_to(np.asarray(w, dtype=np.float64), np.shape(r)).copy())

    # Odd (edge) vertices: 3/8 of each end and 1/8 of each opposite vertex inside; the midpoint on a crease.
    e_ids = np.arange(n_e)
    w_end = np.where(crease, 0.5, 0.375)
    add(n + e_ids, edges[:, 0], w_end)
    add(n + e_ids, edges[:, 1], w_end)
    opposite = faces[:, [2, 0, 1]]  # the vertex across from sides ab, bc, ca
    inner = ~crease[side_edge]
    add(n + side_edge[inner], opposite[inner], 0.125)

    # Even (old) vertices: Warren's weights inside; along a crease 3/4 and 1/8 of its two crease neighbours;
    # where creases meet (corners, more than two crease edges) the vertex stays.
    valence = np.bincount(edges.reshape(-1), minlength=n)
    n_crease = np.bincount(edges[crease].reshape(-1), minlength=n)
    k = np.maximum(valence, 1).astype(np.float64)
    beta = np.where(valence > 3, 3.0 / (8.0 * k), 3.0 / 16.0)
    interior = n_crease == 0
    smooth_crease = n_crease == 2
    self_w = np.where(interior, 1.0 - k * beta, np.where(smooth_crease, 0.75, 1.0))
    add(np.arange(n), np.arange(n), self_w)
    for a, b in ((0, 1), (1, 0)):
        v, u = edges[:, a], edges[:, b]
        m = interior[v]
        add(v[m], u[m], beta[v[m]])
        m = crease & smooth_crease[v]
        add(v[m], u[m], 0.125)
    matrix = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(n + n_e, n)).tocsr()
    ab, bc, ca = (n + side_edge[:, i] for i in range(3))
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    fine = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                           np.stack([ab, bc, ca], 1)])
    return Subdivision(matrix, fine.astype(np.uint32))


def loop_subdivision(faces: np.ndarray, n_vertices: int, levels: int) -> Subdivision:
    """``levels`` Loop subdivisions composed into one matrix (fine vertices × ``n_vertices``); 0 is the identity."""
    if levels < 0:
        raise ValueError(f"subdivision levels must be >= 0, got {levels}")
    matrix = sp.identity(n_vertices, format="csr", dtype=np.float64)
    tri = np.asarray(faces, dtype=np.uint32)
    for _ in range(levels):
        step = loop_step(tri, int(matrix.shape[0]))
        matrix = (step.matrix @ matrix).tocsr()
        tri = step.faces
    return Subdivision(matrix, tri)
