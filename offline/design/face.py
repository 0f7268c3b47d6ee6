"""A head's skin as a design problem: FEM pose problem, actuation space and the thickness warp of the face.

The skin mesh folder (``skin.vtu`` + ``face_units.npz``, as written by ``likeness offline mesh``) gives the outer
surface (kept fixed), the inner surface (moved by the warp) and the attachment node sets (skull and links, locked:
their geometry is what the links grip). Surface coordinates for the MLS warp are the outer surface's two principal
directions (a face seen from the front is a height field over them); each node moves along the inward normal of
its nearest outer-surface vertex (area-weighted normals, smoothed), so a larger height means a thicker skin. On a
layered design mesh (:mod:`offline.design.layered`, a ``columns.npz`` beside the mesh) each node moves by its place
in its column along the widely smoothed outer normal and the warp scales each column's height.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from offline.dataset.fem_problem import FemSkin, FemSpec, material_fields
from offline.fem.mesh import TetMesh
from offline.fem.solve import SolverOptions

from .actuation import ActuationProblem, ActuationSpace
from .mls import place_samples
from .warp import ThicknessWarp, build_warp

#: Rings of normal smoothing for the thickness direction on a layered mesh. Measured on the sample skin's two-layer
#: mesh: the columns' own directions fold 18 elements when every height grows by 2 mm and 2 at ±3 mm contrasts
#: between neighbouring samples; 30 rings fold 1 and 0 (``tests/offline/design/test_design_layered.py``).
WARP_SMOOTHING = 30
#: A layered mesh folder's per-node columns (written by :func:`offline.design.layered.layered_skin_folder`).
COLUMNS_FILE = "columns.npz"


@dataclass(frozen=True, eq=False)
class FaceSkin:
    """The loaded design problem of one head: ``skin`` (the FEM pose problem), the actuation ``space``, the outer
    surface nodes ``outer`` (in face-unit order), the inner surface nodes ``inner``, the attachment nodes
    ``locked`` and the outer surface ``faces`` (indices into ``outer``)."""

    skin: FemSkin
    space: ActuationSpace
    outer: np.ndarray
    inner: np.ndarray
    locked: np.ndarray
    faces: np.ndarray
    mesh_dir: Path

    @property
    def mesh(self) -> TetMesh:
        return self.skin.mesh

    def actuation_problem(self, mesh: TetMesh | None = None, tol_force: float = 1e-8) -> ActuationProblem:
        """Actuation optimization on ``mesh`` (default: the skin as loaded), matching the outer surface."""
        opts = SolverOptions(backend=self.skin.spec.backend, tol_force=tol_force, max_iterations=60,
                             load_steps=1)
        return ActuationProblem(mesh if mesh is not None else self.mesh, self.skin.material, self.space, self.outer,
                                solver=opts)


def load_face(config: str | Path, mesh_dir: str | Path | None = None, backend: str = "auto",
              element_order: int = 1) -> FaceSkin:
    """The design problem of the head ``config`` on its skin (default: ``skin/`` beside the config), on linear or
    quadratic (``element_order`` 2: mid-edge nodes added, same surfaces and node sets) tets."""
    from models.errors import SpecError
    from models.headspec import load_head

    head = load_head(config)
    mdir = Path(mesh_dir) if mesh_dir is not None else Path(config).resolve().parent / "skin"
    linkmap = head.path("linkmap")
    if linkmap is None:
        raise SpecError(str(config), "paths.linkmap", "the head names no link map; actuation needs m(p)")
    spec = FemSpec(config=str(config), mesh=str(mdir), linkmap=str(linkmap), backend=backend,
                   element_order=element_order, **material_fields(head.skin_material()))
    skin = spec.build()
    fu = mdir / "face_units.npz"
    with np.load(fu) as z:
        if "inner_nodes" not in z.files:
            raise SpecError(str(fu), "inner_nodes", "missing: the design needs the inner surface's nodes")
        inner = np.asarray(z["inner_nodes"], dtype=np.int64)
    sets = skin.mesh.node_sets
    locked = np.unique(np.concatenate([np.asarray(sets[skin.spec.skull_set])]
                                      + [np.asarray(sets[s]) for s in skin.moving.values()]))
    space = ActuationSpace.from_head(skin.head, skin.dirichlet)
    return FaceSkin(skin, space, np.asarray(skin.outer), inner, locked, skin.faces(), mdir)


def vertex_normals(pos: np.ndarray, faces: np.ndarray, smooth: int = 3) -> np.ndarray:
    """Unit area-weighted vertex normals of a triangle surface, averaged over ``smooth`` rings."""
    tri = pos[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(pos)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    if smooth:
        import scipy.sparse as sp

        e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(pos), len(pos))).tocsr()
        A = ((A + A.T) > 0).astype(float) + sp.identity(len(pos))
        for _ in range(smooth):
            n = A @ n
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def surface_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and principal axes (rows: the two in-surface directions, then the normal) of a surface's points."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt


def face_warp(face: FaceSkin, *, n_samples: int = 40, width_factor: float = 1.2,
              density: np.ndarray | None = None) -> tuple[ThicknessWarp, np.ndarray]:
    """The MLS thickness warp of the face and each sample's current thickness (m).

    Samples sit on free inner-surface nodes placed by ``density`` (one value per mesh node, e.g.
    :func:`offline.design.warp.strain_density` of the target poses; uniform if None); the kernel width is
    ``width_factor`` × the mean sample spacing over the face's projected area.
    """
    from scipy.spatial import cKDTree

    mesh = face.mesh
    X = np.asarray(mesh.nodes)
    outer_pos = X[face.outer]
    c, axes = surface_frame(outer_pos)
    uv = (X - c) @ axes[:2].T
    n_out = vertex_normals(outer_pos, face.faces)
    tree = cKDTree(outer_pos)
    dist, near = tree.query(X)
    # the outer normals must point away from the inner surface
    _, inner_near = tree.query(X[face.inner])
    if np.mean(np.einsum("ij,ij->i", n_out[inner_near], outer_pos[inner_near] - X[face.inner])) < 0:
        n_out = -n_out
    direction = -n_out[near]
    cand = np.setdiff1d(face.inner, face.locked)
    rho = np.ones(cand.size) if density is None else np.asarray(density, dtype=np.float64)[cand]
    if n_samples < 3 or n_samples > cand.size:
        raise ValueError(f"n_samples must be in [3, {cand.size}] (free inner-surface nodes), got {n_samples}")
    idx = cand[place_samples(uv[cand], rho, n_samples)]
    hull_area = _projected_area(uv[face.outer], face.faces)
    width = width_factor * np.sqrt(hull_area / n_samples)
    columns = _columns(face)
    local = depth = None
    if columns is not None:  # a layered design mesh: move along each node's column, scale its height
        direction, local, depth = columns
        dist = local
    thickness = dist[idx]
    warp = build_warp(mesh, outer=face.outer, inner=face.inner, uv=uv, direction=direction,
                      samples_uv=uv[idx], h_ref=thickness, width=width, locked=face.locked, local_thickness=local,
                      depth=depth)
    return warp, thickness


def _columns(face: FaceSkin) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Each node's column direction, height and place in the column (0 on the whole column of a locked inner
    node) from a layered mesh folder's ``columns.npz``, or None for a mesh without columns. Mid-edge nodes of a
    quadratic mesh take their nearest corner's (the warp then puts them at their edges' midpoints). The direction
    is the outer surface's normal smoothed over ``WARP_SMOOTHING`` rings, at the node's column."""
    from scipy.spatial import cKDTree

    path = face.mesh_dir / COLUMNS_FILE
    if not path.is_file():
        return None
    with np.load(path) as z:
        col, direction = np.asarray(z["column"]), np.asarray(z["direction"])
        height, frac = np.asarray(z["thickness"]), np.asarray(z["fraction"], dtype=np.float64)
    n = len(height)
    X = np.asarray(face.mesh.nodes)
    if n > len(X) or direction.shape != (n, 3) or col.shape != (n,) or frac.shape != (n,):
        raise ValueError(f"{path}: column arrays do not fit a mesh of {len(X)} nodes")
    # move along the outer normals smoothed over many rings rather than along the columns themselves: in a
    # concave crease the columns converge, and thickening along them folds the inner surface within 2 mm
    outer_pos = X[face.outer]
    smooth = vertex_normals(outer_pos, face.faces, smooth=WARP_SMOOTHING)
    sign = np.sign(np.einsum("ij,ij->i", smooth, direction[np.arange(len(face.outer))]).sum())
    direction = sign * smooth[col]
    held = np.zeros(int(col.max()) + 1, dtype=bool)
    held[col[face.locked[face.locked < n]]] = True
    frac = np.where(held[col], 0.0, frac)
    if n < len(X):
        _, near = cKDTree(X[:n]).query(X[n:])
        direction, height = np.concatenate([direction, direction[near]]), np.concatenate([height, height[near]])
        frac = np.concatenate([frac, frac[near]])
    return direction, height, frac


def _projected_area(uv: np.ndarray, faces: np.ndarray) -> float:
    t = uv[faces]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return float(0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum())
