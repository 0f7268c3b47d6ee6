"""A design mesh with several elements through the skin's thickness: the outer surface extruded in layers of tets.

The sample skin's fTetWild mesh is about one linear tet thick (127 interior nodes of 2,316), so the bending and
bulging that thickness controls are barely represented, and a thickness step of a few millimetres folds its flat
elements. This module rebuilds the skin as columns: every outer-surface vertex keeps its position, index and face
units, and a column of ``layers`` + 1 nodes runs from it along the smoothed inward normal to the inner surface
(the local thickness: the distance to the source mesh's inner surface). Each outer triangle and layer gives a
prism, split into three tets with the diagonal rule shared by neighbouring prisms, so the mesh is conforming. A
prism stays positively oriented as long as its column heights stay positive, which is what makes large thickness
steps safe on it. The innermost layer takes the attachment node sets (skull and links) of the nearest source
inner-surface node; memberships are then trimmed so no tet touches two different attachments.

:func:`layered_skin_folder` writes a skin folder (``skin.vtu``, ``face_units.npz``, ``columns.npz``: each node's
column direction and height, which the thickness warp moves along and scales, ``mesh_report.json``) that
:func:`offline.design.face.load_face` and ``likeness offline clone --mesh`` load like the shipped one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from offline.fem.mesh import TetMesh, boundary_faces, signed_volumes, tet_quality

from .face import COLUMNS_FILE, vertex_normals

MESH_FILE = "skin.vtu"
UNITS_FILE = "face_units.npz"
REPORT_FILE = "mesh_report.json"


@dataclass(frozen=True)
class LayeredSkin:
    """The layered mesh and what it was made of: ``thickness`` (S,) column heights (m), ``direction`` (S, 3) unit
    inward column directions, ``columns`` (S, layers + 1) node indices (column k's outer node is k)."""

    mesh: TetMesh
    thickness: np.ndarray
    direction: np.ndarray
    columns: np.ndarray
    dropped_set_nodes: int
    untangled_columns: int = 0
    uncrossed_columns: int = 0

    @property
    def layers(self) -> int:
        """Elements (prism layers) through the thickness."""
        return int(self.columns.shape[1] - 1)

    def node_columns(self) -> dict[str, np.ndarray]:
        """Per node: ``column`` (N,) its column, ``direction`` (N, 3) and ``thickness`` (N,) the column's unit
        direction and height, ``fraction`` (N,) its place in the column (0 outer, 1 inner)."""
        n_col, n_lay = self.columns.shape
        col = np.empty(self.mesh.n_nodes, dtype=np.int64)
        col[self.columns.ravel()] = np.repeat(np.arange(n_col), n_lay)
        frac = np.empty(self.mesh.n_nodes)
        frac[self.columns.ravel()] = np.tile(np.arange(n_lay) / (n_lay - 1), n_col)
        return {"column": col, "direction": self.direction[col], "thickness": self.thickness[col], "fraction": frac}

    @property
    def inner_nodes(self) -> np.ndarray:
        """The innermost layer's node indices (the inner surface)."""
        return self.columns[:, -1].copy()


def prism_tets(triangles: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Tets (3 · T · L, 4) of the prisms between consecutive layers of ``columns`` (S, L + 1) over ``triangles``.

    Each triangle's corners are taken in increasing column index a < b < c; the prism (a, b, c) × [k, k + 1] splits
    into (a_k, b_k, c_k, a_k+1), (b_k, c_k, a_k+1, b_k+1), (c_k, a_k+1, b_k+1, c_k+1): every quad face gets the
    diagonal from the smaller column's upper node to the larger column's lower node, the same from both sides.
    Orientation is not fixed here (see :func:`layered_mesh`).
    """
    tri = np.sort(np.asarray(triangles, dtype=np.int64), axis=1)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    out = []
    for k in range(columns.shape[1] - 1):
        lo, hi = columns[:, k], columns[:, k + 1]
        out += [np.stack([lo[a], lo[b], lo[c], hi[a]], axis=1),
                np.stack([lo[b], lo[c], hi[a], hi[b]], axis=1),
                np.stack([lo[c], hi[a], hi[b], hi[c]], axis=1)]
    return np.concatenate(out)


def column_directions(outer_pos: np.ndarray, triangles: np.ndarray, toward: np.ndarray, smooth: int = 10
                      ) -> np.ndarray:
    """Unit vertex normals of the outer surface smoothed over ``smooth`` rings, signed to point to ``toward``
    (points on the inner side, one per vertex)."""
    n = vertex_normals(outer_pos, triangles, smooth=smooth)
    if np.mean(np.einsum("ij,ij->i", n, toward - outer_pos)) < 0:
        n = -n
    return n


def folded_prisms(outer_pos: np.ndarray, triangles: np.ndarray, end: np.ndarray, min_ratio: float = 0.1
                  ) -> np.ndarray:
    """Indices of the triangles whose prism from the outer surface (``outer_pos``) to the column ends ``end`` has a
    tet oriented against the rest of the mesh (a column crossing its neighbours) or flatter than ``min_ratio`` of
    a right prism's tet (area × mean height / 3)."""
    S = len(outer_pos)
    columns = np.arange(2 * S).reshape(2, S).T
    nodes = np.concatenate([outer_pos, end])
    tri = np.asarray(triangles, dtype=np.int64)
    perm = np.argsort(tri, axis=1)
    even = np.array([list(p) in ([0, 1, 2], [1, 2, 0], [2, 0, 1]) for p in perm.tolist()])
    parity = np.where(even, 1.0, -1.0)
    vol = signed_volumes(nodes, prism_tets(tri, columns)).reshape(3, -1) * parity[None, :]
    ref = np.sign(np.median(vol))
    p = outer_pos[tri]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    height = np.linalg.norm(end - outer_pos, axis=1)[tri].mean(axis=1)
    return np.flatnonzero(np.any(vol * ref <= min_ratio * area * height / 3.0, axis=0))


def untangle_columns(outer_pos: np.ndarray, triangles: np.ndarray, end: np.ndarray, *, shrink: float = 0.85,
                     min_height: float = 5e-4, rounds: int = 40) -> tuple[np.ndarray, int]:
    """Column ends with every folded prism cleared, and how many columns were changed.

    Where the outer surface folds over more sharply than the skin is thick (the lip and lid rims curl inward), the
    smoothed normal runs along the surface and the prism flattens. A corner of a folded prism first turns to the
    surface's own (one-ring) normal; if its prism still folds, its column is shortened by ``shrink`` per round
    (not below ``min_height``): the skin is made locally thinner rather than tangled.
    """
    outer_pos = np.asarray(outer_pos, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    end = np.array(end, dtype=np.float64)
    local = vertex_normals(outer_pos, tri, smooth=1)
    offset = end - outer_pos
    h = np.linalg.norm(offset, axis=1)
    direction = offset / h[:, None]
    local *= np.sign(np.einsum("ij,ij->i", local, direction))[:, None]
    turned = np.zeros(len(end), dtype=bool)
    changed = np.zeros(len(end), dtype=bool)
    for _ in range(rounds):
        bad = folded_prisms(outer_pos, tri, outer_pos + h[:, None] * direction)
        if not bad.size:
            break
        corners = np.unique(tri[bad].ravel())
        turn = corners[~turned[corners]]
        direction[turn] = local[turn]
        turned[turn] = True
        cut = np.setdiff1d(corners, turn)
        h[cut] = np.maximum(h[cut] * shrink, min_height)
        changed[corners] = True
    return outer_pos + h[:, None] * direction, int(changed.sum())


def crossing_columns(outer_pos: np.ndarray, triangles: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Columns (indices of outer vertices) whose end lies on a boundary triangle of the one-layer skin (outer
    surface, column ends, rim walls) that crosses another: where a concave fold brings the column ends of
    distant parts of the surface through each other or through the outer surface."""
    from .mesh_check import self_intersecting_pairs

    S = len(outer_pos)
    columns = np.arange(2 * S).reshape(2, S).T
    nodes = np.concatenate([outer_pos, end])
    faces = boundary_faces(TetMesh(nodes, prism_tets(np.asarray(triangles, dtype=np.int64), columns), {}))
    pairs = self_intersecting_pairs(nodes * 1e3, faces)  # mm, as the mold checks the skin
    ends = faces[np.unique(pairs.ravel())].ravel() if len(pairs) else np.zeros(0, dtype=np.int64)
    return np.unique(ends[ends >= S] - S)


def uncross_columns(outer_pos: np.ndarray, triangles: np.ndarray, end: np.ndarray, *, shrink: float = 0.85,
                    min_height: float = 5e-4, rounds: int = 40) -> tuple[np.ndarray, int]:
    """Column ends shortened (by ``shrink`` per round, not below ``min_height``) until no boundary triangle of the
    skin crosses another, and how many columns were shortened: the skin is made locally thinner rather than
    passing through itself, which no mold could cast. Raises ValueError if ``rounds`` do not clear it."""
    outer_pos = np.asarray(outer_pos, dtype=np.float64)
    end = np.array(end, dtype=np.float64)
    offset = end - outer_pos
    h = np.linalg.norm(offset, axis=1)
    direction = offset / h[:, None]
    changed = np.zeros(len(end), dtype=bool)
    for _ in range(rounds):
        cut = crossing_columns(outer_pos, triangles, outer_pos + h[:, None] * direction)
        if not cut.size:
            return outer_pos + h[:, None] * direction, int(changed.sum())
        h[cut] = np.maximum(h[cut] * shrink, min_height)
        changed[cut] = True
    raise ValueError(f"the layered skin still passes through itself after {rounds} rounds of shortening "
                     f"{int(changed.sum())} columns")


def _inner_surface(mesh: TetMesh, inner: np.ndarray) -> np.ndarray:
    bf = boundary_faces(mesh)
    mask = np.zeros(mesh.n_nodes, dtype=bool)
    mask[inner] = True
    return bf[mask[bf].all(axis=1)]


def layered_mesh(source: TetMesh, outer: np.ndarray, triangles: np.ndarray, inner: np.ndarray, layers: int = 2,
                 smooth: int = 10, set_distance: float = 0.004) -> LayeredSkin:
    """The layered skin of ``source``: outer nodes ``outer`` (S,) with surface ``triangles`` (T, 3, indices into
    ``outer``) extruded in ``layers`` layers down to the inner surface (source nodes ``inner``).

    The innermost node of a column joins the node sets of the nearest source inner node if it lies within
    ``set_distance`` (m) of it. Raises ValueError when a column has no positive height or a tet comes out
    degenerate (the surface folds over itself at this smoothing).
    """
    from scipy.spatial import cKDTree

    from offline.mesh.surface import closest_points

    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    X = np.asarray(source.nodes)
    outer = np.asarray(outer, dtype=np.int64)
    inner = np.asarray(inner, dtype=np.int64)
    outer_pos = X[outer]
    inner_tris = _inner_surface(source, inner)
    if not len(inner_tris):
        raise ValueError("the source mesh has no boundary triangles on its inner surface")
    _, _, h = closest_points(X, inner_tris, outer_pos)
    _, near_inner = cKDTree(X[inner]).query(outer_pos)
    direction = column_directions(outer_pos, triangles, X[inner][near_inner], smooth=smooth)
    if not np.all(h > 0):
        raise ValueError(f"{int(np.sum(h <= 0))} outer vertices lie on the inner surface (zero thickness)")
    S = len(outer)
    columns = np.arange(S * (layers + 1), dtype=np.int64).reshape(layers + 1, S).T  # layer-major numbering
    end, untangled = untangle_columns(outer_pos, triangles, outer_pos + h[:, None] * direction)
    end, uncrossed = uncross_columns(outer_pos, triangles, end)
    h = np.linalg.norm(end - outer_pos, axis=1)
    direction = (end - outer_pos) / h[:, None]
    frac = np.arange(layers + 1) / layers
    nodes = (outer_pos[None, :, :] + frac[:, None, None] * (h[:, None] * direction)[None, :, :]).reshape(-1, 3)
    tets = prism_tets(triangles, columns)
    vol = signed_volumes(nodes, tets)
    bad = folded_prisms(outer_pos, triangles, end)
    if bad.size or np.any(np.abs(vol) <= 1e-15):
        raise ValueError(f"{bad.size} folded prisms and {int(np.sum(np.abs(vol) <= 1e-15))} degenerate tets in "
                         "the layered mesh: the columns cross where the surface curves more sharply than its "
                         "thickness; smooth the normals more")
    neg = vol < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    sets, dropped = _column_sets(source, inner, nodes[columns[:, -1]], columns[:, -1], tets, set_distance)
    mesh = TetMesh(nodes, tets, sets)
    return LayeredSkin(mesh, h, direction, columns, dropped, untangled, uncrossed)


def _column_sets(source: TetMesh, inner: np.ndarray, points: np.ndarray, ids: np.ndarray, tets: np.ndarray,
                 set_distance: float) -> tuple[dict[str, np.ndarray], int]:
    """Node sets on the innermost layer from the nearest source inner node, trimmed so that no tet carries nodes
    of two different sets (the later set in the source's order loses them); returns the sets and the count of
    nodes trimmed."""
    from scipy.spatial import cKDTree

    names = list(source.node_sets)
    label_src = np.full(source.n_nodes, -1, dtype=np.int64)
    for k, name in enumerate(names):
        label_src[np.asarray(source.node_sets[name])] = k
    dist, near = cKDTree(np.asarray(source.nodes)[inner]).query(points)
    n_nodes = int(tets.max()) + 1
    label = np.full(n_nodes, -1, dtype=np.int64)
    label[ids] = np.where(dist <= set_distance, label_src[inner][near], -1)
    dropped = 0
    while True:
        lab = label[tets]  # (M, 4)
        big = np.where(lab >= 0, lab, np.iinfo(np.int64).max).min(axis=1)
        mixed = (lab >= 0) & (lab != big[:, None])
        if not mixed.any():
            break
        losers = np.unique(tets[mixed])
        dropped += int(losers.size)
        label[losers] = -1
    return {name: np.flatnonzero(label == k) for k, name in enumerate(names)}, dropped


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def layered_skin_folder(src_dir: str | Path, out_dir: str | Path, layers: int = 2, smooth: int = 10) -> dict:
    """Write the layered design mesh of the skin folder ``src_dir`` into ``out_dir`` (same face units, outer
    surface and node-set names) and return its report (also written as ``mesh_report.json``, last)."""
    from models.atomic import atomic_path, write_text
    from offline.fem import load_mesh, save_mesh

    src, out = Path(src_dir), Path(out_dir)
    source = load_mesh(src / MESH_FILE)
    with np.load(src / UNITS_FILE) as z:
        units = {k: np.asarray(z[k]) for k in z.files}
    for key in ("surface_nodes", "surface_triangles_local", "inner_nodes"):
        if key not in units:
            raise ValueError(f"{src / UNITS_FILE}: missing {key!r} (needed to extrude the skin)")
    lay = layered_mesh(source, units["surface_nodes"], units["surface_triangles_local"], units["inner_nodes"],
                       layers=layers, smooth=smooth)
    S = len(units["surface_nodes"])
    units.update(surface_nodes=np.arange(S, dtype=np.int64), surface_triangles=units["surface_triangles_local"],
                 inner_nodes=lay.inner_nodes)
    out.mkdir(parents=True, exist_ok=True)
    (out / REPORT_FILE).unlink(missing_ok=True)
    save_mesh(out / MESH_FILE, lay.mesh)
    with atomic_path(out / UNITS_FILE, suffix=".npz") as tmp:
        np.savez(tmp, **units)
    with atomic_path(out / COLUMNS_FILE, suffix=".npz") as tmp:
        np.savez(tmp, **lay.node_columns())
    q = tet_quality(lay.mesh)
    report = {"kind": "layered design mesh", "layers": layers, "normal_smoothing_rings": smooth,
              "source": {"folder": str(src), "skin_vtu_sha256": _sha(src / MESH_FILE),
                         "face_units_sha256": _sha(src / UNITS_FILE), "nodes": source.n_nodes,
                         "tets": source.n_tets},
              "counts": {"nodes": lay.mesh.n_nodes, "tets": lay.mesh.n_tets, "surface_nodes": S,
                         "inner_nodes": int(S)},
              "node_sets": {k: len(v) for k, v in lay.mesh.node_sets.items()},
              "set_nodes_trimmed": lay.dropped_set_nodes,
              "columns_untangled": lay.untangled_columns,
              "columns_shortened_where_the_skin_crossed_itself": lay.uncrossed_columns,
              "thickness_m": {"min": float(lay.thickness.min()), "median": float(np.median(lay.thickness)),
                              "max": float(lay.thickness.max())},
              "quality": {"min": float(q.min()), "median": float(np.median(q))}}
    write_text(out / REPORT_FILE, json.dumps(report, indent=1, sort_keys=True) + "\n")
    return report
