"""Checks that a triangle mesh is a printable solid: watertight, consistently and outward oriented, free of
self-intersections, with its volume.

Watertightness and orientation are edge-based: every undirected edge is used by exactly two triangles, once in each
direction. Self-intersection is tested exactly on the candidate pairs found by a uniform-grid broad phase over the
triangles' bounding boxes: a pair of triangles that share no vertex intersects when an edge of one crosses the
other (segment–triangle test, with a relative tolerance so touching within rounding does not count). Pairs that
share a vertex are left out: two such triangles can only cross each other through a fold, which the orientation
test already refuses where it flips a triangle. Coplanar overlaps of non-adjacent triangles are not detected.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class SolidCheck:
    """Outcome of :func:`check_solid`."""

    watertight: bool
    consistently_oriented: bool
    outward: bool
    self_intersections: int
    volume: float
    components: int
    n_triangles: int

    @property
    def ok(self) -> bool:
        return self.watertight and self.consistently_oriented and self.outward and self.self_intersections == 0

    def as_dict(self) -> dict:
        return {**asdict(self), "ok": self.ok}


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed, consistently oriented mesh (positive when its normals point outward)."""
    t = np.asarray(vertices, dtype=np.float64)[faces]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def _edge_checks(faces: np.ndarray, n_vertices: int) -> tuple[bool, bool, int]:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    und = np.sort(directed, axis=1)
    key = und[:, 0] * n_vertices + und[:, 1]
    _, counts = np.unique(key, return_counts=True)
    watertight = bool(np.all(counts == 2))
    dkey = directed[:, 0] * n_vertices + directed[:, 1]
    consistent = watertight and np.unique(dkey).size == dkey.size  # each directed edge once: opposite directions
    f = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = np.flatnonzero(ks[1:] == ks[:-1])
    a, b = f[order][same], f[order][same + 1]
    g = coo_matrix((np.ones(a.size), (a, b)), shape=(len(faces), len(faces)))
    n_comp = connected_components(g, directed=False)[0]
    return watertight, bool(consistent), int(n_comp)


def _candidate_pairs(tri: np.ndarray, max_pairs: int = 20_000_000) -> np.ndarray:
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    ext = hi - lo
    cell = max(float(np.median(ext.max(axis=1))) * 2.0, 1e-12)
    origin = lo.min(axis=0)
    clo = np.floor((lo - origin) / cell).astype(np.int64)
    chi = np.floor((hi - origin) / cell).astype(np.int64)
    span = chi - clo + 1
    counts = span.prod(axis=1)
    owner = np.repeat(np.arange(len(tri)), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    local = np.arange(counts.sum()) - start
    sy, sz = span[owner, 1], span[owner, 2]
    ix = local // (sy * sz)
    iy = (local // sz) % sy
    iz = local % sz
    c = clo[owner] + np.stack([ix, iy, iz], axis=1)
    dims = c.max(axis=0) + 1
    ckey = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    order = np.argsort(ckey, kind="stable")
    ckey, owner = ckey[order], owner[order]
    bounds = np.flatnonzero(np.r_[True, ckey[1:] != ckey[:-1], True])
    pairs = []
    total = 0
    for s, e in itertools.pairwise(bounds):
        k = e - s
        if k < 2:
            continue
        ids = owner[s:e]
        i, j = np.triu_indices(k, 1)
        pairs.append(np.stack([ids[i], ids[j]], axis=1))
        total += i.size
        if total > max_pairs:
            raise ValueError(f"self-intersection broad phase found over {max_pairs} candidate pairs; mesh too dense")
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    P = np.sort(np.concatenate(pairs), axis=1)
    P = np.unique(P, axis=0)
    # bounding boxes must overlap
    ok = np.all((lo[P[:, 0]] <= hi[P[:, 1]]) & (lo[P[:, 1]] <= hi[P[:, 0]]), axis=1)
    return P[ok]


def _segments_cross(p0: np.ndarray, p1: np.ndarray, tri: np.ndarray, eps: float) -> np.ndarray:
    """Whether segments p0→p1 (K, 3) cross the interiors of triangles (K, 3, 3) (Möller–Trumbore)."""
    d = p1 - p0
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    a = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(d, axis=1) * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    ok = np.abs(a) > 1e-9 * np.maximum(scale, 1e-300)
    a = np.where(ok, a, 1.0)
    s = p0 - tri[:, 0]
    u = np.einsum("ij,ij->i", s, h) / a
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) / a
    t = np.einsum("ij,ij->i", e2, q) / a
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def self_intersecting_pairs(vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """Pairs (P, 2) of vertex-disjoint triangles that cross each other."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    tri = V[F]
    P = _candidate_pairs(tri)
    if P.size == 0:
        return P
    fa, fb = F[P[:, 0]], F[P[:, 1]]
    share = (fa[:, :, None] == fb[:, None, :]).any(axis=(1, 2))
    P = P[~share]
    hit = np.zeros(len(P), dtype=bool)
    for A, B in ((P[:, 0], P[:, 1]), (P[:, 1], P[:, 0])):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hit |= _segments_cross(tri[A, i], tri[A, j], tri[B], eps)
    return P[hit]


def count_self_intersections(vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-7) -> int:
    """Number of pairs of vertex-disjoint triangles that cross each other."""
    return len(self_intersecting_pairs(vertices, faces, eps))


def bad_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges (E, 2) not used by exactly two triangles."""
    F = np.asarray(faces, dtype=np.int64)
    n = int(F.max()) + 1
    und = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    key, counts = np.unique(und[:, 0] * n + und[:, 1], return_counts=True)
    k = key[counts != 2]
    return np.stack([k // n, k % n], axis=1)


def merge_as_stl(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as an STL file carries it: coordinates in single precision, vertices merged by position, triangles
    that collapse dropped."""
    v32 = np.asarray(vertices, dtype=np.float32).astype(np.float64)
    v, inv = np.unique(v32, axis=0, return_inverse=True)
    f = inv.reshape(-1)[np.asarray(faces)]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return v, f[keep]


def check_solid(vertices: np.ndarray, faces: np.ndarray) -> SolidCheck:
    """All checks of one triangle mesh (vertices (V, 3), faces (F, 3))."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"need vertices (V, 3) and a non-empty faces (F, 3), got {V.shape} and {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError("faces index vertices that do not exist")
    watertight, consistent, comps = _edge_checks(F, len(V))
    vol = signed_volume(V, F)
    return SolidCheck(watertight, consistent, vol > 0, count_self_intersections(V, F), abs(vol), comps, len(F))


def check_stl(path) -> SolidCheck:
    """:func:`check_solid` of an STL file (vertices merged by position)."""
    import trimesh

    m = trimesh.load_mesh(str(path), process=False)
    v, inv = np.unique(np.asarray(m.vertices), axis=0, return_inverse=True)
    return check_solid(v, inv.reshape(-1)[np.asarray(m.faces)])
