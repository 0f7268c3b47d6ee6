"""Derivatives of the elastic energy and internal forces with respect to the rest node positions X.

Skin design changes the rest shape, so its sensitivities need ∂W/∂X and the mixed block ∂f/∂X with f = ∂W/∂x.
For a linear tet with edge matrices D_m (rest) and D_s (deformed), F = D_s D_m⁻¹ and W_e = V Ψ(F), V = det D_m / 6:

    ∂W_e/∂D_m = V (Ψ I − Fᵀ P) D_m⁻ᵀ           (an Eshelby-like stress pulled back by D_m)
    f_e = V P D_m⁻ᵀ  (columns: nodes 1..3; node 0 takes minus their sum)

and ∂f_e/∂D_m follows from dV = V tr(D_m⁻¹ dD_m), dF = −F dD_m D_m⁻¹, dP = A : dF, d(D_m⁻ᵀ) = −D_m⁻ᵀ dD_mᵀ D_m⁻ᵀ.
Quadratic (10-node) tets use the same identities at each quadrature point of the isoparametric map: with
J0 = Σ_a X_a ⊗ ∂N_a/∂ξ and G_a = J0⁻ᵀ ∂N_a/∂ξ (the physical shape-function gradients), a rest change dX_b gives
d(w det J0) = w det J0 (G_b · dX_b), dG_a = −G_b (G_a · dX_b) and dF = −F dX_b G_bᵀ. Every material model of
:mod:`offline.fem.materials` is supported.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp

from .energy import (
    _check_x,
    _det3,
    _gather_hessians,
    _mesh_data,
    _pattern,
    _stress,
    _tangent,
    quadrature,
    shape_functions,
)
from .materials import Material
from .mesh import TetMesh


def _check(mesh: TetMesh, x) -> np.ndarray:
    if mesh.order not in (1, 2):
        raise ValueError("rest-shape derivatives are implemented for linear and quadratic tets; "
                         f"this mesh has order {mesh.order}")
    return _check_x(mesh, x)


def _reference(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature weights (Q,) and reference shape-function gradients (Q, n, 3) of an element order."""
    pts, w = quadrature(order)
    return w, np.stack([shape_functions(order, pts[q])[1] for q in range(len(w))])


@nb.njit(cache=True)
def _iso_point(X, x, tets, e, dNr, wq, G, F):
    """At one quadrature point of element e: physical gradients G (n, 3), F (3, 3); returns w det J0."""
    n = tets.shape[1]
    J0 = np.zeros((3, 3))
    for a in range(n):
        for i in range(3):
            for j in range(3):
                J0[i, j] += X[tets[e, a], i] * dNr[a, j]
    det = _det3(J0)
    inv = np.linalg.inv(J0)
    for a in range(n):
        for i in range(3):
            G[a, i] = dNr[a, 0] * inv[0, i] + dNr[a, 1] * inv[1, i] + dNr[a, 2] * inv[2, i]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for a in range(n):
                s += x[tets[e, a], i] * G[a, j]
            F[i, j] = s
    return wq * det


@nb.njit(cache=True)
def _iso_gradient_kernel(X, x, tets, dNref, wref, coef):
    """∂W/∂X for elements of any order: Σ_q w det J0 (Ψ I − Fᵀ P) G_b per node b."""
    n = tets.shape[1]
    g = np.zeros((X.shape[0], 3))
    G = np.empty((n, 3))
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    C = np.empty((3, 3))
    FC = np.empty((3, 3))
    cof = np.empty((3, 3))
    S = np.empty((3, 3))
    for e in range(tets.shape[0]):
        for q in range(wref.shape[0]):
            wd = _iso_point(X, x, tets, e, dNref[q], wref[q], G, F)
            psi = _stress(F, coef, P, C, FC, cof)[0]
            for k in range(3):
                for j in range(3):
                    S[k, j] = -(F[0, k] * P[0, j] + F[1, k] * P[1, j] + F[2, k] * P[2, j]) + (psi if k == j else 0.0)
            for b in range(n):
                for k in range(3):
                    g[tets[e, b], k] += wd * (S[k, 0] * G[b, 0] + S[k, 1] * G[b, 1] + S[k, 2] * G[b, 2])
    return g


@nb.njit(cache=True)
def _iso_mixed_kernel(X, x, tets, dNref, wref, coef, out):
    """out[e, 3a+i, 3b+k] = ∂f_{a,i}/∂X_{b,k} for elements of any order (M, 3n, 3n)."""
    n = tets.shape[1]
    G = np.empty((n, 3))
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    A = np.empty((9, 9))
    C = np.empty((3, 3))
    FC = np.empty((3, 3))
    cof = np.empty((3, 3))
    d = np.empty((3, 9))
    B = np.empty((3, 9, 3))  # B[k, 3i+j, m] = Σ_p A[3i+j, 3p+m] F[p, k]
    PG = np.empty((n, 3))  # PG[a, i] = Σ_j P[i, j] G[a, j]
    dP = np.empty((3, 3))
    out[:, :, :] = 0.0
    for e in range(tets.shape[0]):
        for q in range(wref.shape[0]):
            wd = _iso_point(X, x, tets, e, dNref[q], wref[q], G, F)
            _stress(F, coef, P, C, FC, cof)
            _tangent(F, coef, A, C, FC, cof, d)
            for k in range(3):
                for r in range(9):
                    for m in range(3):
                        B[k, r, m] = A[r, m] * F[0, k] + A[r, 3 + m] * F[1, k] + A[r, 6 + m] * F[2, k]
            for a in range(n):
                for i in range(3):
                    PG[a, i] = P[i, 0] * G[a, 0] + P[i, 1] * G[a, 1] + P[i, 2] * G[a, 2]
            for b in range(n):
                for k in range(3):
                    for r in range(9):  # dP = −B_k G_b
                        dP[r // 3, r % 3] = -(B[k, r, 0] * G[b, 0] + B[k, r, 1] * G[b, 1] + B[k, r, 2] * G[b, 2])
                    col = 3 * b + k
                    for a in range(n):
                        for i in range(3):
                            v = G[b, k] * PG[a, i] - PG[b, i] * G[a, k]
                            v += dP[i, 0] * G[a, 0] + dP[i, 1] * G[a, 1] + dP[i, 2] * G[a, 2]
                            out[e, 3 * a + i, col] += wd * v


@nb.njit(cache=True)
def _edge_inverse(X, tets, e, Dm, Dminv):
    for i in range(3):
        for j in range(3):
            Dm[i, j] = X[tets[e, j + 1], i] - X[tets[e, 0], i]
    det = _det3(Dm)
    Dminv[0, 0] = (Dm[1, 1] * Dm[2, 2] - Dm[1, 2] * Dm[2, 1]) / det
    Dminv[0, 1] = (Dm[0, 2] * Dm[2, 1] - Dm[0, 1] * Dm[2, 2]) / det
    Dminv[0, 2] = (Dm[0, 1] * Dm[1, 2] - Dm[0, 2] * Dm[1, 1]) / det
    Dminv[1, 0] = (Dm[1, 2] * Dm[2, 0] - Dm[1, 0] * Dm[2, 2]) / det
    Dminv[1, 1] = (Dm[0, 0] * Dm[2, 2] - Dm[0, 2] * Dm[2, 0]) / det
    Dminv[1, 2] = (Dm[0, 2] * Dm[1, 0] - Dm[0, 0] * Dm[1, 2]) / det
    Dminv[2, 0] = (Dm[1, 0] * Dm[2, 1] - Dm[1, 1] * Dm[2, 0]) / det
    Dminv[2, 1] = (Dm[0, 1] * Dm[2, 0] - Dm[0, 0] * Dm[2, 1]) / det
    Dminv[2, 2] = (Dm[0, 0] * Dm[1, 1] - Dm[0, 1] * Dm[1, 0]) / det
    return det / 6.0


@nb.njit(cache=True)
def _deformation(x, tets, e, Dminv, F):
    for i in range(3):
        for j in range(3):
            s = 0.0
            for c in range(3):
                s += (x[tets[e, c + 1], i] - x[tets[e, 0], i]) * Dminv[c, j]
            F[i, j] = s


@nb.njit(cache=True)
def _rest_gradient_kernel(X, x, tets, coef):
    M = tets.shape[0]
    g = np.zeros((X.shape[0], 3))
    Dm = np.empty((3, 3))
    Dminv = np.empty((3, 3))
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    C = np.empty((3, 3))
    FC = np.empty((3, 3))
    cof = np.empty((3, 3))
    S = np.empty((3, 3))
    for e in range(M):
        V = _edge_inverse(X, tets, e, Dm, Dminv)
        _deformation(x, tets, e, Dminv, F)
        psi = _stress(F, coef, P, C, FC, cof)[0]
        for i in range(3):  # S = Ψ I − Fᵀ P
            for j in range(3):
                s = -(F[0, i] * P[0, j] + F[1, i] * P[1, j] + F[2, i] * P[2, j])
                S[i, j] = s + (psi if i == j else 0.0)
        for i in range(3):  # G = V S D_m⁻ᵀ; column c goes to node c+1
            for c in range(3):
                v = V * (S[i, 0] * Dminv[c, 0] + S[i, 1] * Dminv[c, 1] + S[i, 2] * Dminv[c, 2])
                g[tets[e, c + 1], i] += v
                g[tets[e, 0], i] -= v
    return g


@nb.njit(cache=True)
def _mixed_blocks_kernel(X, x, tets, coef, out):
    """out[e, 3a+i, 3b+k] = ∂f_{a,i}/∂X_{b,k} for every element (M, 12, 12)."""
    M = tets.shape[0]
    Dm = np.empty((3, 3))
    Dminv = np.empty((3, 3))
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    A = np.empty((9, 9))
    C = np.empty((3, 3))
    FC = np.empty((3, 3))
    cof = np.empty((3, 3))
    d = np.empty((3, 9))
    dF = np.empty((3, 3))
    dP = np.empty((3, 3))
    dH = np.empty((3, 3))
    for e in range(M):
        V = _edge_inverse(X, tets, e, Dm, Dminv)
        _deformation(x, tets, e, Dminv, F)
        _stress(F, coef, P, C, FC, cof)
        _tangent(F, coef, A, C, FC, cof, d)
        for k in range(3):  # perturbed entry (k, l) of D_m: coordinate k of node l+1
            for l in range(3):
                dV = V * Dminv[l, k]
                for i in range(3):
                    for j in range(3):
                        dF[i, j] = -F[i, k] * Dminv[l, j]
                for i in range(3):
                    for j in range(3):
                        s = 0.0
                        for p in range(3):
                            for q in range(3):
                                s += A[3 * i + j, 3 * p + q] * dF[p, q]
                        dP[i, j] = s
                # H = V P D_m⁻ᵀ, H[i, c] = V Σ_j P[i, j] Dminv[c, j]
                for i in range(3):
                    for c in range(3):
                        s = 0.0
                        for j in range(3):
                            s += (dV * P[i, j] + V * dP[i, j]) * Dminv[c, j]
                        # d(D_m⁻ᵀ)[j, c] = −Dminv[c, k] Dminv[l, j]
                        s2 = 0.0
                        for j in range(3):
                            s2 += P[i, j] * Dminv[l, j]
                        dH[i, c] = s - V * s2 * Dminv[c, k]
                for i in range(3):
                    tot = 0.0
                    for c in range(3):
                        out[e, 3 * (c + 1) + i, 3 * (l + 1) + k] = dH[i, c]
                        tot += dH[i, c]
                    out[e, i, 3 * (l + 1) + k] = -tot
        for r in range(12):  # node 0 of X moves every column of D_m by −1
            for k in range(3):
                s = 0.0
                for l in range(3):
                    s += out[e, r, 3 * (l + 1) + k]
                out[e, r, k] = -s


def rest_energy_gradient(mesh: TetMesh, material: Material, x: np.ndarray) -> np.ndarray:
    """∂W/∂X (N, 3): the change of the elastic energy at fixed deformed positions ``x`` per rest-position change (N)."""
    x = _check(mesh, x)
    if mesh.order == 1:
        return _rest_gradient_kernel(np.asarray(mesh.nodes), x, np.asarray(mesh.tets), material.coefficients)
    w, dN = _reference(mesh.order)
    return _iso_gradient_kernel(np.asarray(mesh.nodes), x, np.asarray(mesh.tets), dN, w, material.coefficients)


def mixed_stiffness(mesh: TetMesh, material: Material, x: np.ndarray) -> sp.csr_matrix:
    """∂f/∂X (3N, 3N) CSR with f = ∂W/∂x the internal forces: row 3p+i is f_{p,i}, column 3q+k is X_{q,k}.

    Same sparsity as the tangent stiffness. Not symmetric. Used by adjoint gradients (dq/dX = −λᵀ ∂f/∂X) and
    forward sensitivities (K dx = −∂f/∂X dX) of rest-shape design.
    """
    x = _check(mesh, x)
    d = _mesh_data(mesh)
    pat = _pattern(mesh)
    nd = 3 * mesh.tets.shape[1]
    buf = np.empty((mesh.n_tets, nd, nd))
    if mesh.order == 1:
        _mixed_blocks_kernel(np.asarray(mesh.nodes), x, np.asarray(mesh.tets), material.coefficients, buf)
    else:
        w, dN = _reference(mesh.order)
        _iso_mixed_kernel(np.asarray(mesh.nodes), x, np.asarray(mesh.tets), dN, w, material.coefficients, buf)
    data = np.zeros(pat.indices.size)
    _gather_hessians(mesh.tets, d.adj_ptr, d.adj_elem, d.adj_local, pat.block_base, pat.row_stride, buf, 0,
                         data)
    n = 3 * mesh.n_nodes
    B = sp.csr_matrix((data, pat.indices, pat.indptr), shape=(n, n))
    B.has_sorted_indices = True
    return B
