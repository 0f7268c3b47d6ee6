"""Preconditioned conjugate gradients with a stale factorization as the preconditioner (inexact Newton).

Newton's tangents change little from one iteration to the next, so the Cholesky/PARDISO factor of an earlier
tangent is an excellent preconditioner for the current one: a few back-substitutions (each ~5–10 % of a numeric
factorization) replace a new factorization. :func:`pcg` reports failure instead of raising, so the caller can fall
back to factoring the current matrix.

Inner products are summed with ``einsum`` rather than BLAS: NumPy's OpenBLAS starts its thread pool for vectors
this long, and its spinning threads then compete with the sparse solver's threads for the cores (measured on 2
cores: the preconditioner solves took twice as long).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class KrylovResult:
    """Outcome of :func:`pcg`: the solution (None on failure), iterations used and why it stopped."""

    x: np.ndarray | None
    iterations: int
    reason: str  # "converged", "max_iterations" or "indefinite"


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.einsum("i,i->", a, b))


def pcg(A: sp.spmatrix, b: np.ndarray, precondition: Callable[[np.ndarray], np.ndarray], rtol: float,
        max_iterations: int) -> KrylovResult:
    """Solve symmetric A x = b to ‖b − A x‖ <= rtol ‖b‖ by CG preconditioned with ``precondition`` (≈ A⁻¹).

    Stops with ``x=None`` when A shows non-positive curvature (``indefinite``: the caller should factor A, which
    detects indefiniteness properly) or after ``max_iterations`` preconditioner applications.
    """
    if rtol <= 0 or max_iterations < 1:
        raise ValueError(f"pcg needs rtol > 0 and max_iterations >= 1, got {rtol} and {max_iterations}")
    b = np.asarray(b, dtype=np.float64)
    bnorm = math.sqrt(_dot(b, b))
    x = np.zeros_like(b)
    if bnorm == 0.0:
        return KrylovResult(x, 0, "converged")
    r = b.copy()
    z = precondition(r)
    p = z.copy()
    rz = _dot(r, z)
    for k in range(1, max_iterations + 1):
        Ap = A @ p
        pAp = _dot(p, Ap)
        if not (pAp > 0.0) or not (rz > 0.0):
            return KrylovResult(None, k, "indefinite")
        a = rz / pAp
        x += a * p
        r -= a * Ap
        if math.sqrt(_dot(r, r)) <= rtol * bnorm:
            return KrylovResult(x, k, "converged")
        if k == max_iterations:
            break
        z = precondition(r)
        rz_new = _dot(r, z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return KrylovResult(None, max_iterations, "max_iterations")
