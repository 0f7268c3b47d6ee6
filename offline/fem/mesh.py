"""Tetrahedral meshes for the skin FEM: a frozen data class, structured generators, quality and file I/O.

A :class:`TetMesh` holds rest positions (metres), linear (4-node) or quadratic (10-node, VTK order) tets and named
node sets used for boundary conditions. Meshes are immutable (arrays are read-only) so that cached per-mesh data
(element geometry, sparsity patterns) stays valid; derive new meshes with :meth:`TetMesh.with_node_sets` or
:func:`to_quadratic`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from models.atomic import atomic_path

#: Corner pairs of the six mid-edge nodes of a VTK quadratic tet (nodes 4..9).
QUADRATIC_EDGES: np.ndarray = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)

#: Corner triples of the four faces of a tet, each ordered so that its normal points out of a positive tet.
TET_FACES: np.ndarray = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], dtype=np.int64)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _clean_set(name: str, idx, n_nodes: int) -> np.ndarray:
    arr = np.unique(np.asarray(idx, dtype=np.int64).ravel())
    if arr.size and (arr[0] < 0 or arr[-1] >= n_nodes):
        raise ValueError(f"node set {name!r}: indices must lie in [0, {n_nodes}), got range [{arr[0]}, {arr[-1]}]")
    return _readonly(arr)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """Tet mesh at rest: ``nodes`` (N, 3) metres, ``tets`` (M, 4|10) positively oriented, named ``node_sets``.

    Identity-hashed (two meshes are the same mesh only if they are the same object), so per-mesh caches can key on it.
    """

    nodes: np.ndarray
    tets: np.ndarray
    node_sets: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=np.float64)
        tets = np.asarray(self.tets)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"TetMesh.nodes must have shape (N, 3), got {nodes.shape}")
        if not np.all(np.isfinite(nodes)):
            raise ValueError("TetMesh.nodes contains non-finite values")
        if tets.ndim != 2 or tets.shape[1] not in (4, 10):
            raise ValueError(f"TetMesh.tets must have shape (M, 4) or (M, 10), got {tets.shape}")
        if not np.issubdtype(tets.dtype, np.integer):
            raise ValueError(f"TetMesh.tets must be integer, got dtype {tets.dtype}")
        tets = tets.astype(np.int64)
        if tets.size and (tets.min() < 0 or tets.max() >= len(nodes)):
            raise ValueError(f"TetMesh.tets index out of range [0, {len(nodes)}): [{tets.min()}, {tets.max()}]")
        sets = {str(k): _clean_set(str(k), v, len(nodes)) for k, v in dict(self.node_sets).items()}
        object.__setattr__(self, "nodes", _readonly(nodes))
        object.__setattr__(self, "tets", _readonly(tets))
        object.__setattr__(self, "node_sets", MappingProxyType(sets))

    @property
    def order(self) -> int:
        """Element order: 1 for 4-node, 2 for 10-node tets."""
        return 1 if self.tets.shape[1] == 4 else 2

    @property
    def n_nodes(self) -> int:
        """Number of nodes N."""
        return int(self.nodes.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tets M."""
        return int(self.tets.shape[0])

    def with_node_sets(self, **sets) -> TetMesh:
        """A copy with the given node sets added (or replaced)."""
        merged = dict(self.node_sets)
        merged.update(sets)
        return TetMesh(self.nodes, self.tets, merged)

    def __reduce__(self):
        # MappingProxyType does not pickle; rebuild through the constructor (process pools, Dask)
        return (TetMesh, (np.asarray(self.nodes), np.asarray(self.tets), dict(self.node_sets)))

    def __repr__(self) -> str:
        return (f"TetMesh(n_nodes={self.n_nodes}, n_tets={self.n_tets}, order={self.order}, "
                f"node_sets={sorted(self.node_sets)})")


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tet from its four corners (positive = positively oriented)."""
    p = nodes[tets[:, :4]]
    d = p[:, 1:] - p[:, :1]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def _orient(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap corners 1 and 2 of negatively oriented linear tets."""
    tets = tets.copy()
    neg = signed_volumes(nodes, tets) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return tets


def box_mesh(size: tuple[float, float, float], divisions: tuple[int, int, int], order: int = 1) -> TetMesh:
    """Structured box [0,lx]x[0,ly]x[0,lz] with 6 tets per hex (Kuhn subdivision, conforming).

    Node sets ``x0, x1, y0, y1, z0, z1`` are the nodes on each face.
    """
    lx, ly, lz = (float(s) for s in size)
    nx, ny, nz = (int(d) for d in divisions)
    if min(nx, ny, nz) < 1 or min(lx, ly, lz) <= 0:
        raise ValueError(f"box_mesh: size must be > 0 and divisions >= 1, got size={size}, divisions={divisions}")
    xs, ys, zs = np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1), np.linspace(0, lz, nz + 1)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    nodes = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    def nid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    tets = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        off = np.zeros(3, dtype=np.int64)
        verts = [nid(i, j, k)]
        for axis in perm:
            off[axis] += 1
            verts.append(nid(i + off[0], j + off[1], k + off[2]))
        tets.append(np.stack(verts, axis=1))
    tets = _orient(nodes, np.concatenate(tets).astype(np.int64))
    tol = 1e-9 * max(lx, ly, lz)
    sets = {
        "x0": np.flatnonzero(nodes[:, 0] <= tol), "x1": np.flatnonzero(nodes[:, 0] >= lx - tol),
        "y0": np.flatnonzero(nodes[:, 1] <= tol), "y1": np.flatnonzero(nodes[:, 1] >= ly - tol),
        "z0": np.flatnonzero(nodes[:, 2] <= tol), "z1": np.flatnonzero(nodes[:, 2] >= lz - tol),
    }
    mesh = TetMesh(nodes, tets, sets)
    return _with_order(mesh, order)


def cylinder_mesh(radius: float, height: float, n_radial: int, n_height: int, order: int = 1) -> TetMesh:
    """Cylinder of axis z from z=0 to z=height: a ring-based Delaunay disk extruded in layers, 3 tets per prism.

    ``n_radial`` rings from the axis to the rim (ring k holds 6k nodes); node sets ``bottom`` and ``top``.
    Prisms are split by the global-index rule, so neighbouring prisms share diagonals (conforming).
    """
    from scipy.spatial import Delaunay

    if radius <= 0 or height <= 0 or n_radial < 1 or n_height < 1:
        raise ValueError(f"cylinder_mesh: bad arguments radius={radius}, height={height}, "
                         f"n_radial={n_radial}, n_height={n_height}")
    pts = [np.zeros((1, 2))]
    for k in range(1, n_radial + 1):
        ang = 2.0 * np.pi * np.arange(6 * k) / (6 * k)
        pts.append(radius * k / n_radial * np.column_stack([np.cos(ang), np.sin(ang)]))
    disk = np.vstack(pts)
    tri = np.sort(Delaunay(disk).simplices.astype(np.int64), axis=1)
    n2 = len(disk)
    zs = np.linspace(0.0, height, n_height + 1)
    nodes = np.column_stack([np.tile(disk, (n_height + 1, 1)), np.repeat(zs, n2)])
    tets = []
    for layer in range(n_height):
        a, b, c = (tri[:, i] + layer * n2 for i in range(3))
        at, bt, ct = a + n2, b + n2, c + n2
        tets += [np.column_stack([a, b, c, ct]), np.column_stack([a, b, bt, ct]), np.column_stack([a, at, bt, ct])]
    tets = _orient(nodes, np.concatenate(tets))
    sets = {"bottom": np.arange(n2), "top": n_height * n2 + np.arange(n2)}
    return _with_order(TetMesh(nodes, tets, sets), order)


def _with_order(mesh: TetMesh, order: int) -> TetMesh:
    if order == 1:
        return mesh
    if order == 2:
        return to_quadratic(mesh)
    raise ValueError(f"order must be 1 or 2, got {order}")


def to_quadratic(mesh: TetMesh) -> TetMesh:
    """10-node version of a linear mesh: one shared mid-edge node per edge (straight edges).

    Node sets are extended with the mid-edge nodes whose two end nodes are both in the set.
    """
    if mesh.order == 2:
        return mesh
    tets = np.asarray(mesh.tets)
    edges = tets[:, QUADRATIC_EDGES]  # (M, 6, 2)
    flat = np.sort(edges.reshape(-1, 2), axis=1)
    uniq, inv = np.unique(flat, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = mesh.n_nodes
    mid = 0.5 * (mesh.nodes[uniq[:, 0]] + mesh.nodes[uniq[:, 1]])
    nodes = np.vstack([mesh.nodes, mid])
    tets10 = np.hstack([tets, n + inv.reshape(-1, 6)])
    sets = {}
    for name, idx in mesh.node_sets.items():
        member = np.zeros(n, dtype=bool)
        member[idx] = True
        extra = n + np.flatnonzero(member[uniq[:, 0]] & member[uniq[:, 1]])
        sets[name] = np.concatenate([idx, extra])
    return TetMesh(nodes, tets10, sets)


def boundary_faces(mesh: TetMesh) -> np.ndarray:
    """Boundary triangles (F, 3) of corner nodes, oriented with outward normals."""
    tets = np.asarray(mesh.tets)[:, :4]
    faces = tets[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def tet_quality(mesh: TetMesh) -> np.ndarray:
    """Radius ratio 3 r_in / r_circ of each tet's corner tet (1 for a regular tet, 0 for a degenerate one)."""
    p = mesh.nodes[np.asarray(mesh.tets)[:, :4]]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    vol6 = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    area = 0.0
    for f in TET_FACES:
        area = area + 0.5 * np.linalg.norm(np.cross(p[:, f[1]] - p[:, f[0]], p[:, f[2]] - p[:, f[0]]), axis=1)
    r_in = 0.5 * vol6 / np.maximum(area, 1e-300)  # 3V / A with V = vol6 / 6
    # Circumradius: |a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b) over 2 * 6V... (standard formula)
    num = (np.sum(a * a, 1)[:, None] * np.cross(b, c) + np.sum(b * b, 1)[:, None] * np.cross(c, a)
           + np.sum(c * c, 1)[:, None] * np.cross(a, b))
    r_circ = np.linalg.norm(num, axis=1) / np.maximum(2.0 * vol6, 1e-300)
    return np.where(vol6 > 0, 3.0 * r_in / np.maximum(r_circ, 1e-300), 0.0)


def save_mesh(path, mesh: TetMesh, point_data: Mapping[str, np.ndarray] | None = None) -> None:
    """Write ``mesh`` to a .vtu file (meshio), node sets as 0/1 point data ``set:<name>``; atomic replace.

    ``point_data`` adds per-node fields (e.g. a displacement) to the file.
    """
    import meshio

    path = Path(path)
    cell_type = "tetra" if mesh.order == 1 else "tetra10"
    point_data = dict(point_data or {})
    for name, idx in mesh.node_sets.items():
        flag = np.zeros(mesh.n_nodes, dtype=np.int8)
        flag[idx] = 1
        point_data[f"set:{name}"] = flag
    m = meshio.Mesh(np.asarray(mesh.nodes), [(cell_type, np.asarray(mesh.tets))], point_data=point_data)
    with atomic_path(path, suffix=".vtu") as tmp:
        meshio.write(tmp, m, file_format="vtu")


def load_mesh(path) -> TetMesh:
    """Read a mesh written by :func:`save_mesh` (or any meshio file with tetra/tetra10 cells)."""
    import meshio

    m = meshio.read(Path(path))
    blocks = [c for c in m.cells if c.type in ("tetra", "tetra10")]
    if not blocks:
        raise ValueError(f"{path}: no tetra or tetra10 cells (found {[c.type for c in m.cells]})")
    if len({c.type for c in blocks}) > 1:
        raise ValueError(f"{path}: mixed linear and quadratic tets are not supported")
    tets = np.concatenate([c.data for c in blocks]).astype(np.int64)
    sets = {k[4:]: np.flatnonzero(np.asarray(v) != 0) for k, v in m.point_data.items() if k.startswith("set:")}
    return TetMesh(np.asarray(m.points, dtype=np.float64), tets, sets)
