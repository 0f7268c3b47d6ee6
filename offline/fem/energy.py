"""Elastic energy, internal forces and tangent stiffness of a tet mesh: numba kernels over elements.

Pure functions of ``(mesh, material, x)`` where ``x`` (N, 3) are the deformed node positions. Linear tets use
one-point quadrature (exact), quadratic tets the 4-point degree-2 rule. Per-mesh data (shape-function gradients,
element colouring, the CSR pattern and the element-to-CSR scatter map) is computed once and cached on the mesh
object (meshes are immutable). Element matrices are scattered colour by colour, so assembly runs in parallel
without atomics.

Gravity is an external load: its energy is −Σ f_i·x_i with f_i = m_i g and nodal masses m_i = ρ ∫ N_i dV
(consistent load vector; see :func:`nodal_masses`, :func:`gravity_forces`).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from .materials import Material
from .mesh import TetMesh

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
    from .mesh import QUADRATIC_EDGES

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
    color_ptr: np.ndarray
    color_elems: np.ndarray
    pattern: _Pattern | None = None


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
    color_ptr, color_elems = _color_elements(np.asarray(mesh.tets), mesh.n_nodes)
    return _MeshData(dNdX, wdet, Nq, color_ptr, color_elems)


@nb.njit(cache=True)
def _greedy_colors(tets, n_nodes):
    M, n = tets.shape
    # node -> elements adjacency
    cnt = np.zeros(n_nodes + 1, np.int64)
    for e in range(M):
        for a in range(n):
            cnt[tets[e, a] + 1] += 1
    for i in range(n_nodes):
        cnt[i + 1] += cnt[i]
    fill = cnt[:-1].copy()
    adj = np.empty(cnt[-1], np.int64)
    for e in range(M):
        for a in range(n):
            p = tets[e, a]
            adj[fill[p]] = e
            fill[p] += 1
    color = -np.ones(M, np.int64)
    mark = -np.ones(M + 1, np.int64)  # mark[c] == e: colour c used by a neighbour of e
    for e in range(M):
        for a in range(n):
            p = tets[e, a]
            for k in range(cnt[p], cnt[p + 1]):
                c = color[adj[k]]
                if c >= 0:
                    mark[c] = e
        c = 0
        while mark[c] == e:
            c += 1
        color[e] = c
    return color


def _color_elements(tets: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    color = _greedy_colors(tets, n_nodes)
    order = np.argsort(color, kind="stable")
    counts = np.bincount(color)
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return ptr, order.astype(np.int64)


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
# Material point kernels
# ---------------------------------------------------------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _invariant_derivs(I1, I2, J, coef):
    """Ψ and its first and second derivatives with respect to (I1, I2, J)."""
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
    g = np.empty(3)
    g[0] = f1 * j23
    g[1] = c01 * j43
    db1 = -2.0 / 3.0 * b1 / J
    db2 = -4.0 / 3.0 * b2 / J
    g[2] = f1 * db1 + c01 * db2 + kappa * (J - 1.0)
    H = np.zeros((3, 3))
    H[0, 0] = f2 * j23 * j23
    H[0, 2] = f2 * j23 * db1 + f1 * (-2.0 / 3.0 * j23 / J)
    H[2, 0] = H[0, 2]
    H[1, 2] = c01 * (-4.0 / 3.0 * j43 / J)
    H[2, 1] = H[1, 2]
    H[2, 2] = f2 * db1 * db1 + f1 * (10.0 / 9.0 * b1 / (J * J)) + c01 * (28.0 / 9.0 * b2 / (J * J)) + kappa
    return psi, g, H


@nb.njit(cache=True, inline="always")
def _det3(F):
    return (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
            - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
            + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))


@nb.njit(cache=True, inline="always")
def _cof3(F):
    c = np.empty((3, 3))
    c[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    c[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    c[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    c[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    c[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    c[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    c[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    c[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    c[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    return c


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
def _stress(F, coef):
    """(ψ, P, J) at F; ψ = inf when J <= 0."""
    J = _det3(F)
    P = np.zeros((3, 3))
    if J <= 0.0:
        return np.inf, P, J
    C = F.T @ F
    I1 = C[0, 0] + C[1, 1] + C[2, 2]
    I2 = 0.5 * (I1 * I1 - np.sum(C * C))
    psi, g, _ = _invariant_derivs(I1, I2, J, coef)
    cof = _cof3(F)
    FC = F @ C
    for i in range(3):
        for j in range(3):
            P[i, j] = g[0] * 2.0 * F[i, j] + g[1] * 2.0 * (I1 * F[i, j] - FC[i, j]) + g[2] * cof[i, j]
    return psi, P, J


@nb.njit(cache=True)
def _tangent(F, coef):
    """Material tangent A[3i+J, 3k+L] = ∂²Ψ/∂F_iJ ∂F_kL (9, 9)."""
    J = _det3(F)
    C = F.T @ F
    B = F @ F.T
    I1 = C[0, 0] + C[1, 1] + C[2, 2]
    I2 = 0.5 * (I1 * I1 - np.sum(C * C))
    _, g, H = _invariant_derivs(I1, I2, J, coef)
    cof = _cof3(F)
    FC = F @ C
    d = np.empty((3, 9))
    for i in range(3):
        for j in range(3):
            d[0, 3 * i + j] = 2.0 * F[i, j]
            d[1, 3 * i + j] = 2.0 * (I1 * F[i, j] - FC[i, j])
            d[2, 3 * i + j] = cof[i, j]
    A = np.zeros((9, 9))
    for r in range(9):
        for s in range(9):
            v = 0.0
            for a in range(3):
                for b in range(3):
                    v += H[a, b] * d[a, r] * d[b, s]
            A[r, s] = v
    for r in range(9):
        A[r, r] += 2.0 * g[0]
    # second derivative of J: eps_ikm eps_JLN F_mN
    gJ = g[2]
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
    if g[1] != 0.0:
        g2 = g[1]
        for i in range(3):
            for jj in range(3):
                for k in range(3):
                    for ll in range(3):
                        v = 4.0 * F[i, jj] * F[k, ll] - 2.0 * F[i, ll] * F[k, jj]
                        if i == k:
                            v -= 2.0 * C[jj, ll]
                            if jj == ll:
                                v += 2.0 * I1
                        if jj == ll:
                            v -= 2.0 * B[i, k]
                        A[3 * i + jj, 3 * k + ll] += g2 * v
    return A


# ---------------------------------------------------------------------------------------------------------------
# Element loops
# ---------------------------------------------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def _energy_kernel(x, tets, dNdX, wdet, coef):
    M, Q = wdet.shape
    total = 0.0
    for e in nb.prange(M):
        F = np.empty((3, 3))
        s = 0.0
        for q in range(Q):
            _def_grad(x, tets, dNdX, e, q, F)
            psi, _, _ = _stress(F, coef)
            s += wdet[e, q] * psi
        total += s
    return total


@nb.njit(cache=True, parallel=True)
def _min_det_kernel(x, tets, dNdX):
    M, Q = dNdX.shape[0], dNdX.shape[1]
    out = np.empty(M)
    for e in nb.prange(M):
        F = np.empty((3, 3))
        m = np.inf
        for q in range(Q):
            _def_grad(x, tets, dNdX, e, q, F)
            m = min(m, _det3(F))
        out[e] = m
    return out


@nb.njit(cache=True, parallel=True)
def _force_kernel(x, tets, dNdX, wdet, coef, color_ptr, color_elems):
    _M, Q = wdet.shape
    n = tets.shape[1]
    f = np.zeros((x.shape[0], 3))
    for c in range(color_ptr.shape[0] - 1):
        for t in nb.prange(color_ptr[c], color_ptr[c + 1]):
            e = color_elems[t]
            F = np.empty((3, 3))
            for q in range(Q):
                _def_grad(x, tets, dNdX, e, q, F)
                _, P, _ = _stress(F, coef)
                w = wdet[e, q]
                for a in range(n):
                    p = tets[e, a]
                    for i in range(3):
                        v = 0.0
                        for j in range(3):
                            v += P[i, j] * dNdX[e, q, a, j]
                        f[p, i] += w * v
    return f


@nb.njit(cache=True)
def _element_hessian(x, tets, dNdX, wdet, coef, e, project):
    Q = wdet.shape[1]
    n = tets.shape[1]
    nd = 3 * n
    He = np.zeros((nd, nd))
    F = np.empty((3, 3))
    T = np.empty((9, n, 3))
    for q in range(Q):
        _def_grad(x, tets, dNdX, e, q, F)
        A = _tangent(F, coef)
        w = wdet[e, q]
        for r in range(9):
            for b in range(n):
                for k in range(3):
                    v = 0.0
                    for ll in range(3):
                        v += A[r, 3 * k + ll] * dNdX[e, q, b, ll]
                    T[r, b, k] = v
        for a in range(n):
            for i in range(3):
                for b in range(n):
                    for k in range(3):
                        v = 0.0
                        for jj in range(3):
                            v += dNdX[e, q, a, jj] * T[3 * i + jj, b, k]
                        He[3 * a + i, 3 * b + k] += w * v
    if project:
        # symmetrize then clamp negative eigenvalues to zero
        Hs = 0.5 * (He + He.T)
        lam, V = np.linalg.eigh(Hs)
        if lam[0] < 0.0:
            for r in range(nd):
                if lam[r] < 0.0:
                    lam[r] = 0.0
            return (V * lam) @ V.T, True
        return Hs, False
    return He, False


@nb.njit(cache=True, parallel=True)
def _hessian_kernel(x, tets, dNdX, wdet, coef, color_ptr, color_elems, block_base, row_stride, nnz, project):
    n = tets.shape[1]
    data = np.zeros(nnz)
    n_proj = 0
    for c in range(color_ptr.shape[0] - 1):
        for t in nb.prange(color_ptr[c], color_ptr[c + 1]):
            e = color_elems[t]
            He, projected = _element_hessian(x, tets, dNdX, wdet, coef, e, project)
            if projected:
                n_proj += 1
            for a in range(n):
                p = tets[e, a]
                rs = row_stride[p]
                for b in range(n):
                    base = block_base[e, a, b]
                    for i in range(3):
                        for k in range(3):
                            data[base + i * rs + k] += He[3 * a + i, 3 * b + k]
    return data, n_proj


# ---------------------------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------------------------
def _check_x(mesh: TetMesh, x) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.shape != (mesh.n_nodes, 3):
        raise ValueError(f"x must have shape ({mesh.n_nodes}, 3), got {x.shape}")
    return x


def total_energy(mesh: TetMesh, material: Material, x: np.ndarray) -> float:
    """Elastic energy W(x) = Σ_e ∫ Ψ(F) dV (J); ``inf`` if any quadrature point has J <= 0."""
    d = _mesh_data(mesh)
    return float(_energy_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, d.wdet, material.coefficients))


def internal_forces(mesh: TetMesh, material: Material, x: np.ndarray) -> np.ndarray:
    """Internal nodal forces dW/dx (N, 3) (newtons)."""
    d = _mesh_data(mesh)
    return _force_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, d.wdet, material.coefficients,
                         d.color_ptr, d.color_elems)


def stiffness(mesh: TetMesh, material: Material, x: np.ndarray, project_psd: bool = False) -> sp.csr_matrix:
    """Tangent stiffness d²W/dx² (3N, 3N) CSR, DoF order 3*node + axis; element Hessians PSD-projected if asked."""
    return _stiffness(mesh, material, x, project_psd)[0]


def _stiffness(mesh: TetMesh, material: Material, x: np.ndarray, project_psd: bool) -> tuple[sp.csr_matrix, int]:
    d = _mesh_data(mesh)
    pat = _pattern(mesh)
    data, n_proj = _hessian_kernel(_check_x(mesh, x), mesh.tets, d.dNdX, d.wdet, material.coefficients,
                                   d.color_ptr, d.color_elems, pat.block_base, pat.row_stride,
                                   pat.indices.size, project_psd)
    n = 3 * mesh.n_nodes
    K = sp.csr_matrix((data, pat.indices, pat.indptr), shape=(n, n))
    K.has_sorted_indices = True
    return K, int(n_proj)


def min_jacobian(mesh: TetMesh, x: np.ndarray) -> float:
    """Smallest det F over all quadrature points (<= 0 means an inverted element)."""
    d = _mesh_data(mesh)
    return float(_min_det_kernel(_check_x(mesh, x), mesh.tets, d.dNdX).min())


def element_min_jacobian(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """Smallest det F per element (M,)."""
    d = _mesh_data(mesh)
    return _min_det_kernel(_check_x(mesh, x), mesh.tets, d.dNdX)


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
