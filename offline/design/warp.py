"""The rest shape of a skin as a linear function of sparse thickness samples (MLS warp along a normal field).

The outer surface stays where it is; a node at through-thickness fraction t (0 on the outer surface, 1 on the inner
one, a harmonic blend in between) moves along its unit direction n by t · (H(u) − H_ref(u)), where H is the MLS
interpolation (:mod:`offline.design.mls`) of the sample heights over surface coordinates u. Attachment nodes get
t = 0 and keep their geometry. On quadratic tets the corner nodes move so and each mid-edge node stays at its
edge's midpoint (straight edges: the warped element is as valid as its corner tet).
So X(h) = X_ref + D (h − h_ref) with D = dX/dh a sparse matrix computed once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from offline.fem.mesh import TetMesh

from .mls import mls_matrix, place_samples


def harmonic_depth(mesh: TetMesh, outer: np.ndarray, inner: np.ndarray, locked: np.ndarray | None = None
                   ) -> np.ndarray:
    """Through-thickness fraction t (N,): 0 on ``outer`` and ``locked`` nodes, 1 on ``inner``, harmonic between.

    Uses the corner-edge graph Laplacian with inverse-length weights; ``locked`` wins over ``inner``. On a quadratic
    mesh a mid-edge node takes the mean of its edge's two corners (then the surface and locked values).
    """
    N = mesh.n_nodes
    tets = np.asarray(mesh.tets)[:, :4]
    corner = np.zeros(N, dtype=bool)
    corner[tets.ravel()] = True
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    w = 1.0 / np.linalg.norm(mesh.nodes[pairs[:, 0]] - mesh.nodes[pairs[:, 1]], axis=1)
    Wm = sp.coo_matrix((np.r_[w, w], (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                       shape=(N, N)).tocsr()
    L = sp.diags(np.asarray(Wm.sum(axis=1)).ravel()) - Wm
    t = np.full(N, np.nan)
    t[np.asarray(inner)] = 1.0
    t[np.asarray(outer)] = 0.0
    if locked is not None:
        t[np.asarray(locked)] = 0.0
    if np.intersect1d(outer, inner).size:
        raise ValueError("the outer and inner surfaces share nodes; the thickness direction is undefined there")
    given = t.copy()
    known = ~np.isnan(t)
    unk = np.flatnonzero(~known & corner)
    if unk.size:
        Luu = L[unk][:, unk].tocsc()
        kn = np.flatnonzero(known & corner)
        rhs = -L[unk][:, kn] @ t[kn]
        t[unk] = spla.spsolve(Luu, rhs)
    if mesh.order == 2:
        from offline.fem.mesh import QUADRATIC_EDGES

        full = np.asarray(mesh.tets)
        ends = full[:, :4][:, QUADRATIC_EDGES]  # (M, 6, 2)
        mids = full[:, 4:].ravel()
        t[mids] = 0.5 * (t[ends[..., 0].ravel()] + t[ends[..., 1].ravel()])
        t[known] = given[known]
    return np.clip(t, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class ThicknessWarp:
    """X(h) = X_ref + D (h − h_ref): rest positions of ``mesh`` from S sample heights (metres).

    ``samples_uv`` (S, d) sample positions in surface coordinates, ``width`` the MLS kernel width, ``D`` (3N, S)
    sparse dX/dh, ``depth`` (N,) the through-thickness fraction, ``locked`` (N,) bool attachment nodes.
    """

    mesh: TetMesh
    samples_uv: np.ndarray
    width: float
    h_ref: np.ndarray
    D: sp.csr_matrix
    depth: np.ndarray
    locked: np.ndarray

    @property
    def n_samples(self) -> int:
        """Number of height samples S."""
        return int(self.h_ref.shape[0])

    def rest_positions(self, h: np.ndarray) -> np.ndarray:
        """Rest node positions (N, 3) for sample heights ``h`` (S,)."""
        h = self._check(h)
        return np.asarray(self.mesh.nodes) + (self.D @ (h - self.h_ref)).reshape(-1, 3)

    def rest_mesh(self, h: np.ndarray) -> TetMesh:
        """The warped mesh (same tets and node sets) for sample heights ``h``."""
        return TetMesh(self.rest_positions(h), self.mesh.tets, dict(self.mesh.node_sets))

    def _check(self, h) -> np.ndarray:
        h = np.asarray(h, dtype=np.float64).reshape(-1)
        if h.shape[0] != self.n_samples or not np.all(np.isfinite(h)):
            raise ValueError(f"sample heights must be {self.n_samples} finite values, got shape {h.shape}")
        return h


def build_warp(mesh: TetMesh, *, outer: np.ndarray, inner: np.ndarray, uv: np.ndarray, direction: np.ndarray,
               samples_uv: np.ndarray, h_ref: np.ndarray, width: float, locked: np.ndarray | None = None,
               drop_below: float = 1e-9, local_thickness: np.ndarray | None = None,
               depth: np.ndarray | None = None) -> ThicknessWarp:
    """Precompute the warp of ``mesh``: nodes at surface coordinates ``uv`` (N, d) move along ``direction`` (N, 3).

    ``outer``/``inner`` are node indices of the two surfaces, ``locked`` attachment nodes kept in place, ``h_ref``
    the sample heights that reproduce the mesh as it is. MLS weights below ``drop_below`` of a row's largest are
    dropped to keep D sparse (X(h_ref) stays exact). With ``local_thickness`` (N,), the skin's thickness at each
    node's place, the warp scales thickness instead of shifting it: a node moves by t · c (H(u) − H_ref(u)) with
    c = local_thickness / H_ref(u), so the local thickness becomes local_thickness · H(u) / H_ref(u) and stays
    positive wherever H does (a 1 mm rim next to a 6 mm sample is never thinned by the sample's 3 mm). Still
    linear in h. ``depth`` (N,) replaces the harmonic through-thickness fraction (a layered mesh gives each node its
    place in its column, so the layers keep their order for any positive thickness); locked nodes keep 0.
    """
    N = mesh.n_nodes
    uv = np.asarray(uv, dtype=np.float64)
    if uv.shape[0] != N:
        raise ValueError(f"uv must have one row per node ({N}), got {uv.shape}")
    n = np.asarray(direction, dtype=np.float64)
    if n.shape != (N, 3):
        raise ValueError(f"direction must have shape ({N}, 3), got {n.shape}")
    norms = np.linalg.norm(n, axis=1)
    if np.any(norms <= 0):
        raise ValueError("direction field has zero vectors")
    n = n / norms[:, None]
    h_ref = np.asarray(h_ref, dtype=np.float64).reshape(-1)
    samples_uv = np.atleast_2d(np.asarray(samples_uv, dtype=np.float64))
    if h_ref.shape[0] != samples_uv.shape[0]:
        raise ValueError(f"h_ref has {h_ref.shape[0]} values for {samples_uv.shape[0]} samples")
    locked_idx = np.asarray([] if locked is None else locked, dtype=np.int64)
    if depth is None:
        t = harmonic_depth(mesh, outer, inner, locked_idx)
    else:
        t = np.clip(np.asarray(depth, dtype=np.float64).reshape(-1), 0.0, 1.0)
        if t.shape[0] != N:
            raise ValueError(f"depth must have one value per node ({N}), got {t.shape[0]}")
        t[locked_idx] = 0.0
    moving = np.flatnonzero(t > 0)
    Phi = mls_matrix(uv[moving], samples_uv, width)
    Phi[np.abs(Phi) < drop_below * np.abs(Phi).max(axis=1, keepdims=True)] = 0.0
    if local_thickness is not None:
        lt = np.asarray(local_thickness, dtype=np.float64).reshape(-1)
        if lt.shape[0] != N or not np.all(lt[moving] > 0):
            raise ValueError(f"local_thickness must be {N} values, positive where the warp moves nodes")
        Phi *= (lt[moving] / np.maximum(Phi @ h_ref, 0.1 * float(h_ref.min())))[:, None]
    rows, cols = np.nonzero(Phi)
    vals = Phi[rows, cols]
    node = moving[rows]
    R = np.concatenate([3 * node + k for k in range(3)])
    Cc = np.tile(cols, 3)
    V = np.concatenate([vals * t[node] * n[node, k] for k in range(3)])
    D = sp.csr_matrix((V, (R, Cc)), shape=(3 * N, h_ref.shape[0]))
    if mesh.order == 2:  # mid-edge nodes follow their edge's corners: straight edges, the corner tet's Jacobian
        D = (sp.kron(_midpoint_map(mesh), sp.identity(3)) @ D).tocsr()
    lk = np.zeros(N, dtype=bool)
    lk[locked_idx] = True
    return ThicknessWarp(mesh, samples_uv, float(width), h_ref, D, t, lk)


def _midpoint_map(mesh: TetMesh) -> sp.csr_matrix:
    """(N, N): identity on corner nodes, the mean of the edge's two corners on each mid-edge node."""
    from offline.fem.mesh import QUADRATIC_EDGES

    full = np.asarray(mesh.tets)
    mids, first = np.unique(full[:, 4:].ravel(), return_index=True)
    ends = full[:, :4][:, QUADRATIC_EDGES].reshape(-1, 2)[first]
    corner = np.setdiff1d(np.arange(mesh.n_nodes), mids)
    rows = np.r_[corner, mids, mids]
    cols = np.r_[corner, ends[:, 0], ends[:, 1]]
    vals = np.r_[np.ones(corner.size), np.full(2 * mids.size, 0.5)]
    return sp.csr_matrix((vals, (rows, cols)), shape=(mesh.n_nodes, mesh.n_nodes))


def strain_density(mesh: TetMesh, poses: Sequence[np.ndarray], floor: float = 0.2) -> np.ndarray:
    """A density map (N,) that is larger where the skin deforms most over ``poses`` (deformed positions (N, 3)).

    Per tet the largest Green-strain norm ‖FᵀF − I‖/2 over the poses, averaged onto its nodes, scaled to [0, 1] and
    shifted by ``floor`` (> 0) so that undeformed regions still receive samples.
    """
    from offline.fem.energy import deformation_gradients

    if not poses:
        raise ValueError("strain_density needs at least one deformed pose")
    if not floor > 0:
        raise ValueError(f"strain_density floor must be > 0, got {floor}")
    worst = np.zeros(mesh.n_tets)
    for x in poses:
        F = deformation_gradients(mesh, x)  # (M, Q, 3, 3)
        E = 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(3))
        worst = np.maximum(worst, np.linalg.norm(E, axis=(-2, -1)).max(axis=1))
    tets = np.asarray(mesh.tets)
    total = np.bincount(tets.ravel(), weights=np.repeat(worst, tets.shape[1]), minlength=mesh.n_nodes)
    count = np.bincount(tets.ravel(), minlength=mesh.n_nodes)
    per_node = total / np.maximum(count, 1)
    top = per_node.max()
    return floor + (per_node / top if top > 0 else per_node)


def block_warp(mesh: TetMesh, *, n_samples: int, width: float | None = None,
               density: Callable[[np.ndarray], np.ndarray] | np.ndarray | None = None,
               locked_sets: Sequence[str] = ("x0", "x1")) -> ThicknessWarp:
    """Warp of a :func:`offline.fem.box_mesh` block: outer surface ``z1`` fixed, inner surface ``z0`` moves in −z.

    Heights are the local thickness (the block's height at rest). Samples are placed on the inner surface's free
    nodes by ``density``: a function of (x, y), or one value per mesh node (e.g. :func:`strain_density`), uniform
    if None. The default kernel width is 1.2 × the mean sample spacing.
    """
    for name in ("z0", "z1", *locked_sets):
        if name not in mesh.node_sets:
            raise ValueError(f"block mesh lacks node set {name!r} (has {sorted(mesh.node_sets)})")
    X = np.asarray(mesh.nodes)
    lz = float(X[:, 2].max() - X[:, 2].min())
    locked = np.unique(np.concatenate([mesh.node_sets[s] for s in locked_sets])) if locked_sets else np.zeros(0, int)
    inner = np.asarray(mesh.node_sets["z0"])
    cand = np.setdiff1d(inner, locked)
    uv = X[:, :2]
    if density is None:
        rho = np.ones(cand.size)
    elif callable(density):
        rho = density(uv[cand])
    else:
        rho = np.asarray(density, dtype=np.float64).reshape(-1)
        if rho.shape[0] != mesh.n_nodes:
            raise ValueError(f"density must be a function of (x, y) or one value per node ({mesh.n_nodes}), "
                             f"got {rho.shape[0]} values")
        rho = rho[cand]
    idx = place_samples(uv[cand], rho, n_samples)
    samples_uv = uv[cand[idx]]
    if width is None:
        area = float(np.ptp(X[:, 0]) * np.ptp(X[:, 1]))
        width = 1.2 * np.sqrt(area / n_samples)
    direction = np.tile([0.0, 0.0, -1.0], (mesh.n_nodes, 1))
    return build_warp(mesh, outer=mesh.node_sets["z1"], inner=inner, uv=uv, direction=direction,
                      samples_uv=samples_uv, h_ref=np.full(n_samples, lz), width=width, locked=locked)
