"""Triangle-surface utilities for building the skin shell: topology, normals, smoothing, queries, intersections.

Everything is vectorized NumPy/SciPy on (V, 3) vertex and (T, 3) triangle arrays, small enough for a face.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray, unit: bool = True) -> np.ndarray:
    """Per-triangle normals (right-hand rule); area-weighted (twice the area) unless ``unit``."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    if unit:
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area of each triangle."""
    return 0.5 * np.linalg.norm(triangle_normals(vertices, triangles, unit=False), axis=1)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    n = triangle_normals(vertices, triangles, unit=False)
    out = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(out, triangles[:, i], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def adjacency(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Symmetric vertex adjacency (1 where two vertices share an edge)."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return a.tocsr()


def smooth(values: np.ndarray, adj: sp.csr_matrix, iterations: int, mask: np.ndarray | None = None,
           weight: float = 0.5) -> np.ndarray:
    """Uniform Laplacian smoothing of per-vertex values; only rows where ``mask`` is True change."""
    deg = np.asarray(adj.sum(axis=1)).ravel()
    deg[deg == 0] = 1.0
    out = values.copy()
    for _ in range(iterations):
        avg = (adj @ out) / (deg[:, None] if out.ndim == 2 else deg)
        new = (1.0 - weight) * out + weight * avg
        if mask is None:
            out = new
        else:
            out[mask] = new[mask]
    return out


def grow(adj: sp.csr_matrix, seeds: np.ndarray, rings: int) -> np.ndarray:
    """Boolean mask of the vertices within ``rings`` edges of the seed mask."""
    mask = seeds.astype(bool).copy()
    for _ in range(rings):
        mask = mask | (adj @ mask.astype(np.float64) > 0)
    return mask


def directed_edges(triangles: np.ndarray) -> np.ndarray:
    """All (3T, 2) directed edges in triangle order."""
    return np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Directed edges used by exactly one triangle (in that triangle's orientation)."""
    e = directed_edges(triangles)
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return e[counts[inv.ravel()] == 1]


def boundary_loops(triangles: np.ndarray) -> list[np.ndarray]:
    """Ordered boundary loops (vertex indices, following the triangles' orientation), longest first.

    Raises ValueError if the boundary is not a set of simple loops (a vertex with two outgoing boundary edges).
    """
    be = boundary_edges(triangles)
    nxt: dict[int, int] = {}
    for a, b in be:
        if int(a) in nxt:
            raise ValueError(f"non-manifold boundary at vertex {int(a)}")
        nxt[int(a)] = int(b)
    loops = []
    seen: set[int] = set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        v = nxt[start]
        while v != start:
            if v in seen or v not in nxt:
                raise ValueError(f"boundary does not close at vertex {v}")
            loop.append(v)
            seen.add(v)
            v = nxt[v]
        loops.append(np.asarray(loop, dtype=np.int64))
    loops.sort(key=len, reverse=True)
    return loops


def closed_manifold_problems(triangles: np.ndarray) -> list[str]:
    """Why a triangle set is not a closed, consistently oriented 2-manifold (empty list when it is)."""
    problems = []
    e = directed_edges(triangles)
    key = e[:, 0].astype(np.int64) * (int(e.max()) + 1) + e[:, 1]
    uniq, counts = np.unique(key, return_counts=True)
    if (counts > 1).any():
        problems.append(f"{int((counts > 1).sum())} directed edges used twice (inconsistent orientation)")
    rev = e[:, 1].astype(np.int64) * (int(e.max()) + 1) + e[:, 0]
    missing = ~np.isin(rev, uniq)
    if missing.any():
        problems.append(f"{int(missing.sum())} edges without an opposite half-edge (holes)")
    degenerate = (triangles[:, 0] == triangles[:, 1]) | (triangles[:, 1] == triangles[:, 2]) | (
        triangles[:, 0] == triangles[:, 2])
    if degenerate.any():
        problems.append(f"{int(degenerate.sum())} degenerate triangles")
    return problems


def euler_characteristic(triangles: np.ndarray) -> int:
    """V - E + F of the triangle set (vertices counted as those referenced)."""
    nv = len(np.unique(triangles))
    ne = len(np.unique(np.sort(directed_edges(triangles), axis=1), axis=0))
    return nv - ne + len(triangles)


def enclosed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume enclosed by a closed, outward-oriented triangle surface."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def closest_points(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray,
                   candidates: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on a triangle surface for each query point.

    Returns (triangle index (P,), barycentric coordinates (P, 3), distance (P,)). Candidate triangles are the
    ``candidates`` nearest by centroid, which is exact for the fairly uniform surfaces used here.
    """
    cent = vertices[triangles].mean(axis=1)
    k = min(candidates, len(triangles))
    _, cand = cKDTree(cent).query(points, k=k)
    cand = np.asarray(cand).reshape(len(points), k)
    p = np.repeat(points, k, axis=0)
    tri = triangles[cand.ravel()]
    bary = _closest_on_triangles(p, vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]])
    q = np.einsum("ij,ijk->ik", bary, vertices[tri])
    d = np.linalg.norm(q - p, axis=1).reshape(len(points), k)
    best = d.argmin(axis=1)
    rows = np.arange(len(points))
    flat = rows * k + best
    return cand[rows, best], bary[flat], d[rows, best]


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest point on triangles (a, b, c) to points p (row-wise)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    out = np.empty((n, 3))
    done = np.zeros(n, dtype=bool)

    def put(mask: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> None:
        m = mask & ~done
        out[m, 0], out[m, 1], out[m, 2] = u[m], v[m], w[m]
        done[m] = True

    one, zero = np.ones(n), np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), one, zero, zero)
        put((d3 >= 0) & (d4 <= d3), zero, one, zero)
        t = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, zero)
        put((d6 >= 0) & (d5 <= d6), zero, zero, one)
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, zero, t)
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), zero, 1 - t, t)
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        put(np.ones(n, dtype=bool), 1 - v - w, v, w)
    return out


def self_intersections(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Indices of triangles that intersect another triangle they share no vertex with.

    Two triangles in general position intersect iff an edge of one crosses the other, so every edge is tested
    against the nearby triangles (KD-tree on centroids) with a segment/triangle test.
    """
    edges = np.unique(np.sort(directed_edges(triangles), axis=1), axis=0)
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    tv = vertices[triangles]
    cent = tv.mean(axis=1)
    rad = np.linalg.norm(tv - cent[:, None, :], axis=2).max()
    mid = 0.5 * (a + b)
    half = 0.5 * np.linalg.norm(b - a, axis=1)
    tree = cKDTree(cent)
    trad = np.linalg.norm(tv - cent[:, None, :], axis=2).max(axis=1)
    hits = tree.query_ball_point(mid, half + rad, return_sorted=False)
    lens = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
    if lens.sum() == 0:
        return np.zeros(0, dtype=np.int64)
    pairs_e = np.repeat(np.arange(len(edges)), lens)
    pairs_t = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if h])
    # exact sphere test with each triangle's own radius
    close = np.linalg.norm(mid[pairs_e] - cent[pairs_t], axis=1) <= half[pairs_e] + trad[pairs_t]
    pairs_e, pairs_t = pairs_e[close], pairs_t[close]
    pe = pairs_e
    pt = pairs_t
    shares = (triangles[pt] == edges[pe, 0:1]).any(axis=1) | (triangles[pt] == edges[pe, 1:2]).any(axis=1)
    pe, pt = pe[~shares], pt[~shares]
    hit = _segments_cross_triangles(a[pe], b[pe], tv[pt, 0], tv[pt, 1], tv[pt, 2])
    if not hit.any():
        return np.zeros(0, dtype=np.int64)
    # the triangles containing the crossing edges are involved as well
    edge_tris = _edge_triangles(triangles, edges[pe[hit]])
    return np.unique(np.concatenate([pt[hit], edge_tris]))


def _edge_triangles(triangles: np.ndarray, edges: np.ndarray) -> np.ndarray:
    de = np.sort(directed_edges(triangles), axis=1)
    tri_of = np.tile(np.arange(len(triangles)), 3)
    m = int(max(de.max(), edges.max())) + 1
    key = de[:, 0].astype(np.int64) * m + de[:, 1]
    want = np.sort(edges, axis=1)
    return np.unique(tri_of[np.isin(key, want[:, 0].astype(np.int64) * m + want[:, 1])])


def _segments_cross_triangles(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                              eps: float = 1e-12) -> np.ndarray:
    """Row-wise: does segment pq cross triangle abc (Moller-Trumbore, parameter strictly inside [0, 1])?"""
    d = q - p
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - a
    u = np.einsum("ij,ij->i", s, h) * inv
    qv = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, qv) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1)
