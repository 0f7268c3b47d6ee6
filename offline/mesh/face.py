"""Cut the skin's outer surface out of the hm08 base mesh: the face region with mouth and eyes opened.

The face region (every body quad touching a vertex that some face unit moves) is a disk whose mouth leads into a
closed mouth cavity and whose eyes lead into closed socket cups. Those cavities are found by ambient occlusion:
rays are cast over each quad's normal hemisphere and large connected sets of quads from which few rays escape are
dropped. The rim is then cleaned (spikes, non-manifold vertices, stray pieces) and the quads split into triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from offline.mesh.anny import AnnyFace
from offline.mesh.surface import boundary_loops

DM_TO_M = 0.1


@dataclass(frozen=True)
class CutParams:
    """How the openings are found: rays per quad, escape fraction below which a quad is occluded, and the
    smallest connected set of occluded quads that counts as a cavity (smaller sets are surface creases).
    ``min_depth_m`` then trims the region's sides towards the ears: every quad corner must lie at z >= that
    (metres, +z out of the face)."""

    min_depth_m: float = 0.09
    n_rays: int = 32
    escape_threshold: float = 0.3
    min_cavity_quads: int = 50
    widen_rings: int = 2


@dataclass(frozen=True)
class FaceSurface:
    """The outer skin surface in metres: triangles oriented outward (+z is the face's front), ``source`` maps
    each vertex to its hm08 vertex, ``loops`` are the ordered boundary loops (rim first)."""

    vertices: np.ndarray
    triangles: np.ndarray
    source: np.ndarray
    loops: tuple[np.ndarray, ...]
    n_cavity_quads: int

    @property
    def area(self) -> float:
        """Surface area (m^2)."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def face_region(face: AnnyFace) -> np.ndarray:
    """Body quads (Q, 4) touching a vertex that some face unit moves."""
    moved = np.zeros(len(face.vertices), dtype=bool)
    for offsets in face.face_units.values():
        moved |= np.abs(offsets).sum(axis=1) > 0
    return face.quads[moved[face.quads].any(axis=1)]


def quad_adjacency(quads: np.ndarray) -> sp.csr_matrix:
    """Quad-to-quad adjacency through shared edges."""
    e = np.sort(np.stack([quads, np.roll(quads, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    fid = np.repeat(np.arange(len(quads)), 4)
    m = int(quads.max()) + 1
    key = e[:, 0].astype(np.int64) * m + e[:, 1]
    order = np.argsort(key, kind="stable")
    k = key[order]
    same = np.nonzero(k[1:] == k[:-1])[0]
    a, b = fid[order[same]], fid[order[same + 1]]
    adj = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(len(quads), len(quads))).tocsr()
    return ((adj + adj.T) > 0).astype(np.int8).tocsr()


def quad_normals(vertices: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Unit normals of (possibly non-planar) quads from the cross product of their diagonals."""
    n = np.cross(vertices[quads[:, 2]] - vertices[quads[:, 0]], vertices[quads[:, 3]] - vertices[quads[:, 1]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def hemisphere_directions(n: int) -> np.ndarray:
    """``n`` deterministic, evenly spread unit directions on the +z hemisphere (Fibonacci spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n
    r = np.sqrt(1.0 - z * z)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def escape_fractions(vertices: np.ndarray, quads: np.ndarray, n_rays: int) -> np.ndarray:
    """Fraction of hemisphere rays from each quad's centre that leave the region without hitting it."""
    import vtk  # heavy; only needed here

    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    pts = vtk.vtkPoints()
    for p in vertices:
        pts.InsertNextPoint(*p)
    cells = vtk.vtkCellArray()
    for t in tris:
        cells.InsertNextCell(3, [int(t[0]), int(t[1]), int(t[2])])
    poly = vtk.vtkPolyData()
    poly.SetPoints(pts)
    poly.SetPolys(cells)
    tree = vtk.vtkOBBTree()
    tree.SetDataSet(poly)
    tree.BuildLocator()
    normals = quad_normals(vertices, quads)
    centres = vertices[quads].mean(axis=1)
    dirs = hemisphere_directions(n_rays)
    reach = 2.0 * float(np.linalg.norm(np.ptp(vertices[quads].reshape(-1, 3), axis=0)))
    step = 1e-4 * reach
    hits = vtk.vtkPoints()
    out = np.empty(len(quads))
    for i, (nz, c) in enumerate(zip(normals, centres, strict=True)):
        helper = np.array([1.0, 0.0, 0.0]) if abs(nz[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        tx = np.cross(nz, helper)
        tx /= np.linalg.norm(tx)
        ty = np.cross(nz, tx)
        world = dirs @ np.stack([tx, ty, nz])
        origin = c + step * nz
        free = sum(tree.IntersectWithLine(origin, origin + reach * d, hits, None) == 0 for d in world)
        out[i] = free / n_rays
    return out


def drop_cavities(quads: np.ndarray, escape: np.ndarray, params: CutParams) -> tuple[np.ndarray, int]:
    """Remove connected sets of occluded quads of at least ``min_cavity_quads``; returns (kept quads, n dropped)."""
    occluded = np.nonzero(escape < params.escape_threshold)[0]
    adj = quad_adjacency(quads)[occluded][:, occluded]
    n, labels = connected_components(adj, directed=False)
    sizes = np.bincount(labels, minlength=n)
    drop = np.zeros(len(quads), dtype=bool)
    drop[occluded[sizes[labels] >= params.min_cavity_quads]] = True
    if params.widen_rings:
        # widen each opening by rings of quads sharing a vertex: removes the lid and lip margins that curl inward
        n_vert = int(quads.max()) + 1
        incid = sp.coo_matrix((np.ones(quads.size), (np.repeat(np.arange(len(quads)), 4), quads.ravel())),
                              shape=(len(quads), n_vert)).tocsr()
        share = (incid @ incid.T).tocsr()
        for _ in range(params.widen_rings):
            drop = drop | (share @ drop.astype(np.float64) > 0)
    keep = ~drop
    return quads[keep], int(drop.sum())


def clean_rim(quads: np.ndarray, max_rounds: int = 50) -> np.ndarray:
    """Make the quad region a single manifold piece with simple boundary loops.

    Repeats until nothing changes: keep the largest connected piece, drop quads hanging on by one edge, and at
    each vertex where the region touches itself keep only the largest fan of quads.
    """
    for _ in range(max_rounds):
        before = len(quads)
        adj = quad_adjacency(quads)
        n, labels = connected_components(adj, directed=False)
        if n > 1:
            quads = quads[labels == np.bincount(labels).argmax()]
            continue
        degree = np.asarray(adj.sum(axis=1)).ravel()
        spikes = degree <= 1
        if spikes.any():
            quads = quads[~spikes]
            continue
        quads = _split_nonmanifold_vertices(quads)
        if len(quads) == before:
            return quads
    raise RuntimeError("face rim cleaning did not converge")


def _split_nonmanifold_vertices(quads: np.ndarray) -> np.ndarray:
    """Drop the smaller fans at vertices whose incident quads form more than one edge-connected fan."""
    n_vert = int(quads.max()) + 1
    incid = sp.coo_matrix((np.ones(quads.size), (quads.ravel(), np.repeat(np.arange(len(quads)), 4))),
                          shape=(n_vert, len(quads))).tocsr()
    adj = quad_adjacency(quads)
    drop: set[int] = set()
    for v in range(n_vert):
        faces = incid.indices[incid.indptr[v]:incid.indptr[v + 1]]
        if len(faces) < 2:
            continue
        sub = adj[faces][:, faces]
        n, labels = connected_components(sub, directed=False)
        if n > 1:
            # edges through v only: two quads sharing an edge not at v still count as one fan, which is fine
            biggest = np.bincount(labels).argmax()
            drop.update(int(f) for f in faces[labels != biggest])
    if not drop:
        return quads
    keep = np.ones(len(quads), dtype=bool)
    keep[sorted(drop)] = False
    return quads[keep]


def triangulate(vertices: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Split each quad along its shorter diagonal, keeping the orientation."""
    d02 = np.linalg.norm(vertices[quads[:, 0]] - vertices[quads[:, 2]], axis=1)
    d13 = np.linalg.norm(vertices[quads[:, 1]] - vertices[quads[:, 3]], axis=1)
    use02 = d02 <= d13
    t1 = np.where(use02[:, None], quads[:, [0, 1, 2]], quads[:, [0, 1, 3]])
    t2 = np.where(use02[:, None], quads[:, [0, 2, 3]], quads[:, [1, 2, 3]])
    return np.concatenate([t1, t2])


def cut_face(face: AnnyFace, params: CutParams = CutParams()) -> FaceSurface:
    """Cut the face region out of the base mesh, open mouth and eyes, and return the outer surface in metres."""
    region = face_region(face)
    escape = escape_fractions(face.vertices, region, params.n_rays)
    kept, n_dropped = drop_cavities(region, escape, params)
    front = face.vertices[:, 2] * DM_TO_M >= params.min_depth_m  # +z points out of the face
    kept = kept[front[kept].all(axis=1)]
    kept = clean_rim(kept)
    used = np.unique(kept)
    remap = np.full(len(face.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts = face.vertices[used] * DM_TO_M
    tris = triangulate(verts, remap[kept])
    normals = quad_normals(verts, remap[kept])
    if normals[:, 2].mean() < 0:  # make the surface face forward (outward from the head)
        tris = tris[:, ::-1].copy()
    loops = tuple(boundary_loops(tris))
    return FaceSurface(vertices=verts, triangles=tris, source=used, loops=loops, n_cavity_quads=n_dropped)
