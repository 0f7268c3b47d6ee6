"""Elastic energy, internal forces and tangent stiffness of a tet mesh: numba kernels over elements.

Pure functions of ``(mesh, material, x)`` where ``x`` (N, 3) are the deformed node positions. Linear tets use
one-point quadrature (exact), quadratic tets the 4-point degree-2 rule. Per-mesh data (shape-function gradients,
node-to-element adjacency, the CSR pattern and the element-to-CSR scatter map) is computed once and cached on the
mesh object (meshes are immutable). Element Hessians are computed in parallel into a buffer and gathered into the
CSR data in parallel by node (each node owns its rows), so assembly needs no atomics and only two parallel regions.

Gravity is an external load: its energy is −Σ f_i·x_i with f_i = m_i g and nodal masses m_i = ρ ∫ N_i dV
(consistent load vector; see :func:`nodal_masses`, :func:`gravity_forces`).
"""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Iterator
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from .materials import Material
from .mesh import QUADRATIC_EDGES, TetMesh

# ---------------------------------------------------------------------------------------------------------------
# Reference element and quadrature
# ---------------------------------------------------------------------------------------------------------------
_DL = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
_QA, _QB = 0.5854101966249685, 0.1381966011250105


def quadrature(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric points (Q, 4) and weights (Q,) on the reference tet (weights sum to 1/6)."""
    if order == 1:
        return np.full((1, 4), 0.25), np.array([1.0 / 6.0])
    pts = np.full((4, 4), _QB)
    np.fill_diagonal(pts, _QA)
    return pts, np.full(4, 1.0 / 24.0)


def shape_functions(order: int, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values (n,) and reference gradients (n, 3) of the element's shape functions at barycentric point ``bary``."""
    L = np.asarray(bary, dtype=np.float64)
    if order == 1:
        return L.copy(), _DL.copy()
    N = np.empty(10)
    dN = np.empty((10, 3))
    for i in range(4):
        N[i] = L[i] * (2.0 * L[i] - 1.0)
        dN[i] = (4.0 * L[i] - 1.0) * _DL[i]
    for m, (i, j) in enumerate(QUADRATIC_EDGES):
        N[4 + m] = 4.0 * L[i] * L[j]
        dN[4 + m] = 4.0 * (L[j] * _DL[i] + L[i] * _DL[j])
    return N, dN


# ---------------------------------------------------------------------------------------------------------------
# Per-mesh cache
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class _Pattern:
    indptr: np.ndarray
    indices: np.ndarray
    block_base: np.ndarray  # (M, n, n) data index of entry (3a, 3b) of each element block, minus row offset
    row_stride: np.ndarray  # (N,) 3 * number of node neighbours: data offset between rows 3p+i and 3p+i+1


@dataclass
class _MeshData:
    dNdX: np.ndarray  # (M, Q, n, 3)
    wdet: np.ndarray  # (M, Q) quadrature weight * rest volume jacobian
    Nq: np.ndarray  # (Q, n) shape function values at the quadrature points
    adj_ptr: np.ndarray  # (N+1,) node -> (element, local index) adjacency, CSR
    adj_elem: np.ndarray
    adj_local: np.ndarray
    pattern: _Pattern | None = None
    colors: tuple[np.ndarray, np.ndarray] | None = None  # (color_ptr, elements ordered by colour)


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _mesh_data(mesh: TetMesh) -> _MeshData:
    data = _CACHE.get(mesh)
    if data is None:
        data = _build_mesh_data(mesh)
        _CACHE[mesh] = data
    return data


def _build_mesh_data(mesh: TetMesh) -> _MeshData:
    order = mesh.order
    pts, w = quadrature(order)
    X = np.asarray(mesh.nodes)[np.asarray(mesh.tets)]  # (M, n, 3)
    M, n = mesh.n_tets, mesh.tets.shape[1]
    dNdX = np.empty((M, len(w), n, 3))
    wdet = np.empty((M, len(w)))
    Nq = np.empty((len(w), n))
    for q in range(len(w)):
        N, dN = shape_functions(order, pts[q])
        Nq[q] = N
        J0 = np.einsum("mai,aj->mij", X, dN)  # dX/dxi
        det = np.linalg.det(J0)
        if np.any(det <= 0):
            bad = np.flatnonzero(det <= 0)
            raise ValueError(f"mesh has {bad.size} inverted or degenerate tets (first: tet {bad[0]}, "
                             f"det={det[bad[0]]:.3e}); tets must be positively oriented")
        Jinv = np.linalg.inv(J0)
        dNdX[:, q] = np.einsum("aj,mji->mai", dN, Jinv)
        wdet[:, q] = w[q] * det
    tets = np.asarray(mesh.tets)
    flat = tets.ravel()
    order_ = np.argsort(flat, kind="stable")
    adj_ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=mesh.n_nodes))]).astype(np.int64)
    adj_elem = (order_ // n).astype(np.int64)
    adj_local = (order_ % n).astype(np.int64)
    return _MeshData(dNdX, wdet, Nq, adj_ptr, adj_elem, adj_local)


@nb.njit(cache=True)
def _greedy_colors(tets, n_nodes):
    """Colour elements so that no two of one colour share a node (greedy, first free colour of 64); returns each
    element's colour, or -1 for all when 64 colours do not suffice."""
    M, n = tets.shape
    used = np.zeros(n_nodes, dtype=np.uint64)
    color = np.empty(M, dtype=np.int64)
    for e in range(M):
        mask = np.uint64(0)
        for a in range(n):
            mask |= used[tets[e, a]]
        c = 0
        while c < 64 and (mask >> np.uint64(c)) & np.uint64(1):
            c += 1
        if c == 64:
            color[:] = -1
            return color
        color[e] = c
        bit = np.uint64(1) << np.uint64(c)
        for a in range(n):
            used[tets[e, a]] |= bit
    return color


def _colors(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray] | None:
    """Elements grouped into colours that share no node (cached): each colour's element Hessians can be added into
    the matrix in parallel without two threads touching one row. None if the mesh needs more than 64 colours."""
    data = _mesh_data(mesh)
    if data.colors is None:
        color = _greedy_colors(np.ascontiguousarray(mesh.tets), mesh.n_nodes)
        if color.size and color[0] < 0:
            data.colors = (np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64))
        else:
            order = np.argsort(color, kind="stable").astype(np.int64)
            ptr = np.concatenate([[0], np.cumsum(np.bincount(color, minlength=int(color.max(initial=-1)) + 1))])
            data.colors = (ptr.astype(np.int64), order)
    ptr, order = data.colors
    return None if order.size != mesh.n_tets else (ptr, order)


def _pattern(mesh: TetMesh) -> _Pattern:
    data = _mesh_data(mesh)
    if data.pattern is None:
        data.pattern = _build_pattern(np.asarray(mesh.tets), mesh.n_nodes)
    return data.pattern


def _build_pattern(tets: np.ndarray, n_nodes: int) -> _Pattern:
    M, n = tets.shape
    p = np.repeat(tets, n, axis=1).ravel()  # (M*n*n) row node of entry (a, b)
    q = np.tile(tets, (1, n)).ravel()
    keys = p * n_nodes + q
    uniq, inv = np.unique(keys, return_inverse=True)
    up, uq = uniq // n_nodes, uniq % n_nodes
    deg = np.bincount(up, minlength=n_nodes).astype(np.int64)
    bptr = np.concatenate([[0], np.cumsum(deg)]).astype(np.int64)
    rank = np.arange(uniq.size, dtype=np.int64) - bptr[up]
    block_base_u = 9 * bptr[up] + 3 * rank
    block_base = block_base_u[inv.ravel()].reshape(M, n, n)
    row_stride = 3 * deg
    # CSR arrays
    nnz = 9 * uniq.size
    rows_start = (9 * bptr[:-1])[:, None] + np.arange(3)[None, :] * row_stride[:, None]  # (N, 3)
    indptr = np.empty(3 * n_nodes + 1, dtype=np.int64)
    indptr[:-1] = rows_start.ravel()
    indptr[-1] = nnz
    cols3 = (3 * uq[:, None] + np.arange(3)[None, :]).ravel()  # per block, 3 columns, in CSR order per node row
    indices = np.empty(nnz, dtype=np.int64)
    # row 3p+i holds, for each neighbour q of p (sorted), columns 3q..3q+2
    for i in range(3):
        seg_start = np.repeat(9 * bptr[:-1] + i * row_stride, 3 * deg)
        within = np.arange(3 * uniq.size) - np.repeat(3 * bptr[:-1], 3 * deg)
        indices[seg_start + within] = cols3
    if nnz < 2**31 - 1:
        indptr, indices = indptr.astype(np.int32), indices.astype(np.int32)
    return _Pattern(indptr, indices, block_base, row_stride)


# ---------------------------------------------------------------------------------------------------------------
# Material point kernels (allocation-free: scratch arrays are passed in)
# ---------------------------------------------------------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _invariant_derivs(I1, I2, J, coef):
    """Ψ, its gradient (g1, g2, gJ) and Hessian entries (h11, h1J, h2J, hJJ) with respect to (I1, I2, J)."""
    c10, c20, c30, c01, kappa = coef[0], coef[1], coef[2], coef[3], coef[4]
    j23 = J ** (-2.0 / 3.0)
    j43 = j23 * j23
    b1 = I1 * j23
    b2 = I2 * j43
    a = b1 - 3.0
    f = c10 * a + c20 * a * a + c30 * a * a * a
    f1 = c10 + 2.0 * c20 * a + 3.0 * c30 * a * a
    f2 = 2.0 * c20 + 6.0 * c30 * a
    psi = f + c01 * (b2 - 3.0) + 0.5 * kappa * (J - 1.0) ** 2
    db1 = -2.0 / 3.0 * b1 / J
    db2 = -4.0 / 3.0 * b2 / J
    g1 = f1 * j23
    g2 = c01 * j43
    gJ = f1 * db1 + c01 * db2 + kappa * (J - 1.0)
    h11 = f2 * j23 * j23
    h1J = f2 * j23 * db1 + f1 * (-2.0 / 3.0 * j23 / J)
    h2J = c01 * (-4.0 / 3.0 * j43 / J)
    hJJ = f2 * db1 * db1 + f1 * (10.0 / 9.0 * b1 / (J * J)) + c01 * (28.0 / 9.0 * b2 / (J * J)) + kappa
    return psi, g1, g2, gJ, h11, h1J, h2J, hJJ


@nb.njit(cache=True, inline="always")
def _det3(F):
    return (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
            - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
            + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))


@nb.njit(cache=True, inline="always")
def _kinematics(F, C, FC, cof):
    """Fill C = FᵀF, FC = F C and cof(F); return (I1, I2, J)."""
    for i in range(3):
        for j in range(3):
            C[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
    for i in range(3):
        for j in range(3):
            FC[i, j] = F[i, 0] * C[0, j] + F[i, 1] * C[1, j] + F[i, 2] * C[2, j]
    cof[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    cof[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    cof[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    cof[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    cof[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    cof[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    cof[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    cof[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    cof[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    I1 = C[0, 0] + C[1, 1] + C[2, 2]
    cc = 0.0
    for i in range(3):
        for j in range(3):
            cc += C[i, j] * C[i, j]
    J = F[0, 0] * cof[0, 0] + F[0, 1] * cof[0, 1] + F[0, 2] * cof[0, 2]
    return I1, 0.5 * (I1 * I1 - cc), J


@nb.njit(cache=True, inline="always")
def _def_grad(x, tets, dNdX, e, q, F):
    n = tets.shape[1]
    for i in range(3):
        for j in range(3):
            F[i, j] = 0.0
    for a in range(n):
        p = tets[e, a]
        for i in range(3):
            xi = x[p, i]
            for j in range(3):
                F[i, j] += xi * dNdX[e, q, a, j]


@nb.njit(cache=True)
def _stress(F, coef, P, C, FC, cof):
    """Write P = ∂Ψ/∂F; return (ψ, J); ψ = inf when J <= 0."""
    I1, I2, J = _kinematics(F, C, FC, cof)
    if J <= 0.0:
        for i in range(3):
            for j in range(3):
                P[i, j] = 0.0
        return np.inf, J
    psi, g1, g2, gJ, _, _, _, _ = _invariant_derivs(I1, I2, J, coef)
    for i in range(3):
        for j in range(3):
            P[i, j] = 2.0 * g1 * F[i, j] + 2.0 * g2 * (I1 * F[i, j] - FC[i, j]) + gJ * cof[i, j]
    return psi, J


@nb.njit(cache=True)
def _tangent(F, coef, A, C, FC, cof, d):
    """Write the material tangent A[3i+J, 3k+L] = ∂²Ψ/∂F_iJ ∂F_kL (9, 9); ``d`` is (3, 9) scratch."""
    I1, I2, J = _kinematics(F, C, FC, cof)
    _, g1, g2, gJ, h11, h1J, h2J, hJJ = _invariant_derivs(I1, I2, J, coef)
    for i in range(3):
        for j in range(3):
            d[0, 3 * i + j] = 2.0 * F[i, j]
            d[1, 3 * i + j] = 2.0 * (I1 * F[i, j] - FC[i, j])
            d[2, 3 * i + j] = cof[i, j]
    for r in range(9):
        u0 = h11 * d[0, r] + h1J * d[2, r]
        u1 = h2J * d[2, r]
        u2 = h1J * d[0, r] + h2J * d[1, r] + hJJ * d[2, r]
        for s in range(9):
            A[r, s] = u0 * d[0, s] + u1 * d[1, s] + u2 * d[2, s]
        A[r, r] += 2.0 * g1
    # gJ * ∂²J/∂F∂F = gJ * ε_ikm ε_JLN F_mN
    for i in range(3):
        for k in range(3):
            if i == k:
                continue
            m = 3 - i - k
            sik = 1.0 if (k - i) % 3 == 1 else -1.0
            for jj in range(3):
                for ll in range(3):
                    if jj == ll:
                        continue
                    nn = 3 - jj - ll
                    sjl = 1.0 if (ll - jj) % 3 == 1 else -1.0
                    A[3 * i + jj, 3 * k + ll] += gJ * sik * sjl * F[m, nn]
    if g2 != 0.0:
        # g2 * ∂²I2/∂F∂F with ∂²I2 = 4 F_iJ F_kL + 2 I1 δ_ik δ_JL − 2 δ_ik C_JL − 2 F_iL F_kJ − 2 B_ik δ_JL
        for i in range(3):
            for k in range(3):
                Bik = F[i, 0] * F[k, 0] + F[i, 1] * F[k, 1] + F[i, 2] * F[k, 2]
                for jj in range(3):
                    for ll in range(3):
                        v = 4.0 * F[i, jj] * F[k, ll] - 2.0 * F[i, ll] * F[k, jj]
                        if i == k:
                            v -= 2.0 * C[jj, ll]
                            if jj == ll:
                                v += 2.0 * I1
                        if jj == ll:
                            v -= 2.0 * Bik
                        A[3 * i + jj, 3 * k + ll] += g2 * v


# ---------------------------------------------------------------------------------------------------------------
# Element loops: parallel over chunks of elements, scratch allocated once per chunk
# ---------------------------------------------------------------------------------------------------------------
def _n_chunks(M: int) -> int:
    """Work chunks for M elements (computed outside numba: reading the thread count there blocks caching)."""
    return max(1, min(M, 16 * nb.get_num_threads()))


@nb.njit(cache=True, parallel=True)
def _energy_kernel(x, tets, dNdX, wdet, coef, nc):
    M, Q = wdet.shape
    size = (M + nc - 1) // nc
    total = 0.0
    for c in nb.prange(nc):
        F = np.empty((3, 3))
        C = np.empty((3, 3))
        FC = np.empty((3, 3))
        cof = np.empty((3, 3))
        s = 0.0
        for e in range(c * size, min(M, (c + 1) * size)):
            for q in range(Q):
                _def_grad(x, tets, dNdX, e, q, F)
                I1, I2, J = _kinematics(F, C, FC, cof)
                if J <= 0.0:
                    s += np.inf
                else:
                    psi = _invariant_derivs(I1, I2, J, coef)[0]
                    s += wdet[e, q] * psi
        total += s
    return total


@nb.njit(cache=True, parallel=True)
def _min_det_kernel(x, tets, dNdX, nc):
    M, Q = dNdX.shape[0], dNdX.shape[1]
    out = np.empty(M)
    size = (M + nc - 1) // nc
    for c in nb.prange(nc):
        F = np.empty((3, 3))
        for e in range(c * size, min(M, (c + 1) * size)):
            m = np.inf
            for q in range(Q):
                _def_grad(x, tets, dNdX, e, q, F)
                m = min(m, _det3(F))
            out[e] = m
    return out


@nb.njit(cache=True, parallel=True)
def _force_kernel(x, tets, dNdX, wdet, coef, nc):
    M, Q = wdet.shape
    n = tets.shape[1]
    fe = np.zeros((M, n, 3))
    size = (M + nc - 1) // nc
    for c in nb.prange(nc):
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        C = np.empty((3, 3))
        FC = np.empty((3, 3))
        cof = np.empty((3, 3))
        for e in range(c * size, min(M, (c + 1) * size)):
            for q in range(Q):
                _def_grad(x, tets, dNdX, e, q, F)
                _stress(F, coef, P, C, FC, cof)
                w = wdet[e, q]
                for a in range(n):
                    for i in range(3):
                        fe[e, a, i] += w * (P[i, 0] * dNdX[e, q, a, 0] + P[i, 1] * dNdX[e, q, a, 1]
                                            + P[i, 2] * dNdX[e, q, a, 2])
    f = np.zeros((x.shape[0], 3))
    for e in range(M):
        for a in range(n):
            p = tets[e, a]
            for i in range(3):
                f[p, i] += fe[e, a, i]
    return f


#: PSD projection of the tangent (numba kernels' ``project`` argument): none, per quadrature point, per element.
PROJECT_NONE, PROJECT_QUADRATURE, PROJECT_ELEMENT = 0, 1, 2


@nb.njit(cache=True)
def _element_hessian(x, tets, dNdX, wdet, coef, e, He, F, A, C, FC, cof, d, T, project=0):
    """Write the Hessian of element e into He (3n, 3n), made positive semidefinite with ``project``
    (:data:`PROJECT_QUADRATURE`: each quadrature point's material tangent; :data:`PROJECT_ELEMENT`: He itself).
    Returns whether anything was projected."""
    Q = wdet.shape[1]
    n = tets.shape[1]
    He[:, :] = 0.0
    projected = False
    for q in range(Q):
        _def_grad(x, tets, dNdX, e, q, F)
        _tangent(F, coef, A, C, FC, cof, d)
        if project == PROJECT_QUADRATURE and _project_psd_small(A):
            projected = True
        w = wdet[e, q]
        for r in range(9):
            for b in range(n):
                g0, g1, g2 = dNdX[e, q, b, 0], dNdX[e, q, b, 1], dNdX[e, q, b, 2]
                for k in range(3):
                    T[r, b, k] = w * (A[r, 3 * k] * g0 + A[r, 3 * k + 1] * g1 + A[r, 3 * k + 2] * g2)
        for a in range(n):  # upper block triangle only (b >= a); A is symmetric, so He is
            g0, g1, g2 = dNdX[e, q, a, 0], dNdX[e, q, a, 1], dNdX[e, q, a, 2]
            for i in range(3):
                for b in range(a, n):
                    for k in range(3):
                        He[3 * a + i, 3 * b + k] += g0 * T[3 * i, b, k] + g1 * T[3 * i + 1, b, k] + g2 * T[
                            3 * i + 2, b, k]
    for a in range(n):
        for b in range(a + 1, n):
            for i in range(3):
                for k in range(3):
                    He[3 * b + k, 3 * a + i] = He[3 * a + i, 3 * b + k]
    if project == PROJECT_ELEMENT and _project_psd(He):
        projected = True
    return projected


@nb.njit(cache=True, inline="always")
def _hessian_scratch(n):
    """Scratch arrays of :func:`_element_hessian` for elements of ``n`` nodes (one set per worker chunk)."""
    return (np.empty((3, 3)), np.empty((9, 9)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty((3, 9)), np.empty((9, n, 3)))


@nb.njit(cache=True)
def _project_psd(H):
    """Clamp negative eigenvalues of symmetric H to zero in place (H = V max(λ, 0) Vᵀ); True if any was negative."""
    Hs = 0.5 * (H + H.T)
    lam, V = np.linalg.eigh(Hs)
    if lam[0] >= 0.0:
        H[:, :] = Hs
        return False
    for r in range(lam.shape[0]):
        if lam[r] < 0.0:
            lam[r] = 0.0
    H[:, :] = (V * lam) @ V.T
    return True


@nb.njit(cache=True)
def _is_positive_definite(A):
    """Whether symmetric A has a Cholesky factor (about 300 flops for 9 x 9)."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if s <= 0.0:
            return False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    return True


@nb.njit(cache=True)
def _project_psd_small(A):
    """Clamp negative eigenvalues of the symmetric material tangent A (9, 9) to zero in place; True if any was.

    Projecting each quadrature point's tangent, rather than the assembled element Hessian (30 x 30 for quadratic
    tets), keeps the element Hessian positive semidefinite at a fraction of the cost: most points of an element
    far from equilibrium are definite and pass the Cholesky test alone."""
    if _is_positive_definite(A):
        return False
    return _project_psd(A)


@nb.njit(cache=True, parallel=True)
def _element_hessians(x, tets, dNdX, wdet, coef, e0, project, out, nc):
    """Element Hessians of elements e0 .. e0 + len(out) into ``out``; returns how many had a tangent projected."""
    B = out.shape[0]
    n = tets.shape[1]
    size = (B + nc - 1) // nc
    n_proj = 0
    for c in nb.prange(nc):
        F, A, C, FC, cof, d, T = _hessian_scratch(n)
        cnt = 0
        for t in range(c * size, min(B, (c + 1) * size)):
            if _element_hessian(x, tets, dNdX, wdet, coef, e0 + t, out[t], F, A, C, FC, cof, d, T, project):
                cnt += 1
        n_proj += cnt
    return n_proj


@nb.njit(cache=True, parallel=True)
def _gather_hessians(tets, adj_ptr, adj_elem, adj_local, block_base, row_stride, Hbuf, e0, data):
    """Add buffered element Hessians into CSR ``data``; parallel over nodes (each owns its three rows)."""
    n = tets.shape[1]
    e1 = e0 + Hbuf.shape[0]
    for p in nb.prange(adj_ptr.shape[0] - 1):
        rs = row_stride[p]
        for k in range(adj_ptr[p], adj_ptr[p + 1]):
            e = adj_elem[k]
            if e < e0 or e >= e1:
                continue
            a = adj_local[k]
            for b in range(n):
                base = block_base[e, a, b]
                for i in range(3):
                    for kk in range(3):
                        data[base + i * rs + kk] += Hbuf[e - e0, 3 * a + i, 3 * b + kk]


@nb.njit(cache=True, parallel=True)
def _assemble_colored(x, tets, dNdX, wdet, coef, project, color_ptr, order, block_base, row_stride, data):
    """Add every element Hessian straight into CSR ``data``, one colour at a time, the elements of a colour in
    parallel (they share no node, so no two threads write one row); returns how many had a tangent projected."""
    n = tets.shape[1]
    nd = 3 * n
    n_proj = 0
    for c in range(color_ptr.shape[0] - 1):
        lo, hi = color_ptr[c], color_ptr[c + 1]
        count = hi - lo
        nc = min(count, 64)
        size = (count + nc - 1) // nc
        for ch in nb.prange(nc):
            F, A, C, FC, cof, d, T = _hessian_scratch(n)
            He = np.empty((nd, nd))
            cnt = 0
            for t in range(lo + ch * size, min(hi, lo + (ch + 1) * size)):
                e = order[t]
                if _element_hessian(x, tets, dNdX, wdet, coef, e, He, F, A, C, FC, cof, d, T, project):
                    cnt += 1
                for a in range(n):
                    rs = row_stride[tets[e, a]]
                    for b in range(n):
                        base = block_base[e, a, b]
                        for i in range(3):
                            row = base + i * rs
                            for k in range(3):
                                data[row + k] += He[3 * a + i, 3 * b + k]
            n_proj += cnt
    return n_proj


#: Bytes of element-Hessian buffer per assembly batch (meshes that need more than 64 colours only).
_HESSIAN_BUFFER_BYTES = 16 * 2**20


# ---------------------------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------------------------
def prepare(mesh: TetMesh, stiffness_pattern: bool = True) -> None:
    """Precompute and cache the per-mesh data (shape-function gradients, adjacency, CSR pattern, element colours)
    now.

    Raises ValueError naming the first inverted tet. Later kernel calls on this mesh object reuse the cache.
    """
    _mesh_data(mesh)
    if stiffness_pattern:
        _pattern(mesh)
        _colors(mesh)


def _check_x(mesh: TetMesh, x) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.shape != (mesh.n_nodes, 3):
        raise ValueError(f"x must have shape ({mesh.n_nodes}, 3), got {x.shape}")
    return x


def total_energy(mesh: TetMesh, material: Material, x: np.ndarray) -> float:
    """Elastic energy W(x) = Σ_e ∫ Ψ(F) dV (J); ``inf`` if any quadrature point has J <= 0."""
    d = _mesh_data(mesh)
    return float(_energy_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, d.wdet, material.coefficients,
                                _n_chunks(mesh.n_tets)))


def internal_forces(mesh: TetMesh, material: Material, x: np.ndarray) -> np.ndarray:
    """Internal nodal forces dW/dx (N, 3) (newtons)."""
    d = _mesh_data(mesh)
    return _force_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, d.wdet, material.coefficients,
                         _n_chunks(mesh.n_tets))


def stiffness(mesh: TetMesh, material: Material, x: np.ndarray, project_psd: bool | str = False
              ) -> sp.csr_matrix:
    """Tangent stiffness d²W/dx² (3N, 3N) CSR, DoF order 3*node + axis.

    ``project_psd`` makes every element Hessian, and so K, positive semidefinite (the Newton fallback far from
    equilibrium): ``True`` or ``"quadrature"`` projects each quadrature point's material tangent ∂²Ψ/∂F² (9 x 9,
    mostly definite: cheap), ``"element"`` each element Hessian as a whole (30 x 30 for quadratic tets: the nearest
    PSD element Hessian, several times slower)."""
    return _stiffness(mesh, material, x, project_psd)[0]


def _projection_mode(project_psd: bool | str) -> int:
    if project_psd is False or project_psd is None:
        return PROJECT_NONE
    if project_psd is True or project_psd == "quadrature":
        return PROJECT_QUADRATURE
    if project_psd == "element":
        return PROJECT_ELEMENT
    raise ValueError(f"project_psd must be False, True, 'quadrature' or 'element', got {project_psd!r}")


def _stiffness(mesh: TetMesh, material: Material, x: np.ndarray, project_psd: bool | str
               ) -> tuple[sp.csr_matrix, int]:
    project_psd = _projection_mode(project_psd)
    d = _mesh_data(mesh)
    pat = _pattern(mesh)
    x = _check_x(mesh, x)
    data = np.zeros(pat.indices.size)
    coef = material.coefficients
    colors = _colors(mesh)
    if colors is not None:
        n_proj = _assemble_colored(x, mesh.tets, d.dNdX, d.wdet, coef, project_psd, colors[0], colors[1],
                                   pat.block_base, pat.row_stride, data)
    else:  # batches of element Hessians, then gathered by node
        nd = 3 * mesh.tets.shape[1]
        batch = max(1, min(mesh.n_tets, _HESSIAN_BUFFER_BYTES // (8 * nd * nd)))
        buf = np.empty((batch, nd, nd))
        n_proj = 0
        for e0 in range(0, mesh.n_tets, batch):
            b = min(batch, mesh.n_tets - e0)
            n_proj += _element_hessians(x, mesh.tets, d.dNdX, d.wdet, coef, e0, project_psd, buf[:b],
                                        _n_chunks(b))
            _gather_hessians(mesh.tets, d.adj_ptr, d.adj_elem, d.adj_local, pat.block_base, pat.row_stride,
                             buf[:b], e0, data)
    n = 3 * mesh.n_nodes
    K = sp.csr_matrix((data, pat.indices, pat.indptr), shape=(n, n))
    K.has_sorted_indices = True
    return K, int(n_proj)


def min_jacobian(mesh: TetMesh, x: np.ndarray) -> float:
    """Smallest det F over all quadrature points (<= 0 means an inverted element)."""
    d = _mesh_data(mesh)
    return float(_min_det_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, _n_chunks(mesh.n_tets)).min())


def element_min_jacobian(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """Smallest det F per element (M,)."""
    d = _mesh_data(mesh)
    return _min_det_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, _n_chunks(mesh.n_tets))


def nodal_masses(mesh: TetMesh, material: Material) -> np.ndarray:
    """Consistent nodal masses m_i = ρ ∫ N_i dV (N,) (kg); for 10-node tets the corner values are negative."""
    d = _mesh_data(mesh)
    per = np.einsum("mq,qa->ma", d.wdet, d.Nq) * material.density
    return np.bincount(np.asarray(mesh.tets).ravel(), weights=per.ravel(), minlength=mesh.n_nodes)


def gravity_forces(mesh: TetMesh, material: Material, gravity) -> np.ndarray:
    """External nodal forces f_i = m_i g (N, 3) for gravity vector ``g`` (m/s²); external energy is −Σ f_i·x_i."""
    g = np.asarray(gravity, dtype=np.float64).reshape(3)
    return nodal_masses(mesh, material)[:, None] * g[None, :]


def deformation_gradients(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """Deformation gradient F at every quadrature point (M, Q, 3, 3) (NumPy; for post-processing and tests)."""
    d = _mesh_data(mesh)
    x = _check_x(mesh, x)
    return np.einsum("mai,mqaj->mqij", x[np.asarray(mesh.tets)], d.dNdX)


@contextlib.contextmanager
def kernel_threads(n: int) -> Iterator[None]:
    """Run the numba kernels on at most ``n`` threads inside the block; the previous count is restored.

    Changes the count at run time (``numba.set_num_threads``) instead of the environment, which numba reads
    only once: per-task thread limits (dataset workers, small meshes) stay local to the code that asks.
    """
    before = nb.get_num_threads()
    nb.set_num_threads(max(1, min(int(n), nb.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        nb.set_num_threads(before)
