"""Pluggable sparse direct solvers for symmetric FEM matrices: CHOLMOD, PARDISO, SciPy SuperLU.

A :class:`SparseSolver` is made once per sparsity pattern (:func:`make_solver`); ``solver.factor(A)`` reuses the
symbolic analysis (fill-reducing ordering) and returns a :class:`Factorization` whose ``solve(b)`` can be called any
number of times (Newton steps, adjoint solves). Cholesky backends raise :class:`NotPositiveDefinite` when the matrix
is not positive definite, which the Newton solver uses to switch to a PSD-projected tangent.

``"auto"`` picks CHOLMOD (scikit-sparse) if importable, else PARDISO (pypardiso), else SuperLU (always available);
when CHOLMOD is linked against the reference (unoptimised) BLAS and PARDISO is present, PARDISO comes first.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
from abc import ABC, abstractmethod

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

BACKENDS = ("cholmod", "pardiso", "superlu")


class NotPositiveDefinite(RuntimeError):
    """The matrix handed to a Cholesky backend is not (numerically) positive definite."""


def _has(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _cholmod_uses_reference_blas() -> bool:
    """True when the loaded CHOLMOD runs on the unoptimised reference BLAS (Linux: read the process's mappings).

    Supernodal CHOLMOD spends its time in BLAS; on reference BLAS it is several times slower than PARDISO.
    """
    try:
        maps = open("/proc/self/maps").read()  # noqa: SIM115
    except OSError:
        return False
    # Debian/Ubuntu alternatives: the reference BLAS lives in .../blas/libblas.so.3, OpenBLAS/BLIS/ATLAS elsewhere
    paths = {line.split()[-1] for line in maps.splitlines() if "libblas.so" in line}
    return bool(paths) and all(os.path.basename(os.path.dirname(p)) == "blas" for p in paths)


@functools.lru_cache(maxsize=1)
def _available_backends() -> tuple[str, ...]:
    return tuple(_probe_backends())


def available_backends() -> list[str]:
    """Backends importable here, fastest first (CHOLMOD, then PARDISO; PARDISO first if CHOLMOD has slow BLAS)."""
    return list(_available_backends())


def _probe_backends() -> list[str]:
    out = []
    if _has("sksparse"):
        try:
            import sksparse.cholmod  # noqa: F401

            out.append("cholmod")
        except ImportError:
            pass
    if _has("pypardiso"):
        try:
            import pypardiso  # noqa: F401

            out.append("pardiso")
        except (ImportError, OSError):
            pass
    if out[:2] == ["cholmod", "pardiso"] and _cholmod_uses_reference_blas():
        out[:2] = ["pardiso", "cholmod"]
    out.append("superlu")
    return out


def resolve_backend(name: str) -> str:
    """Concrete backend name for ``name`` (``auto`` or one of :data:`BACKENDS`); clear error if unavailable."""
    avail = available_backends()
    if name == "auto":
        return avail[0]
    if name not in BACKENDS:
        raise ValueError(f"unknown linear solver backend {name!r}; choose one of {('auto', *BACKENDS)}")
    if name not in avail:
        raise ValueError(f"linear solver backend {name!r} is not available here (available: {avail})")
    return name


class Factorization(ABC):
    """A factored matrix A: ``solve(b)`` returns A⁻¹ b for b of shape (n,) or (n, k)."""

    backend: str = ""

    @abstractmethod
    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve A y = b."""


class SparseSolver(ABC):
    """Factors matrices of one sparsity pattern, reusing the symbolic analysis between calls."""

    backend: str = ""
    precision: str = "double"

    @abstractmethod
    def factor(self, A: sp.spmatrix) -> Factorization:
        """Numeric factorization of symmetric A (same pattern as previous calls)."""


# --------------------------------------------------------------------------------------------------- CHOLMOD
class _CholmodFactorization(Factorization):
    backend = "cholmod"

    def __init__(self, factor) -> None:
        self._f = factor

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._f.solve_A(np.asarray(b, dtype=np.float64))


class _CholmodSolver(SparseSolver):
    backend = "cholmod"

    def __init__(self) -> None:
        self._symbolic = None
        self._pattern_key = None

    def factor(self, A: sp.spmatrix) -> Factorization:
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

        A = sp.csc_matrix(A)
        key = (A.shape, A.nnz)
        if self._symbolic is None or key != self._pattern_key:
            self._symbolic = analyze(A, mode="supernodal", ordering_method="default")  # LL^T: reports indefinite
            self._pattern_key = key
        f = self._symbolic.copy()
        try:
            f.cholesky_inplace(A)
        except CholmodNotPositiveDefiniteError as exc:
            raise NotPositiveDefinite(str(exc)) from exc
        return _CholmodFactorization(f)


# --------------------------------------------------------------------------------------------------- PARDISO
class _PardisoFactorization(Factorization):
    backend = "pardiso"

    def __init__(self, owner: _PardisoSolver, upper: sp.csr_matrix, generation: int) -> None:
        self._owner = owner
        self._upper = upper
        self._generation = generation

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._generation != self._owner.generation:
            raise RuntimeError("this PARDISO factorization was replaced by a newer factor() call on its solver")
        b = np.asarray(b, dtype=np.float64)
        bf = np.asfortranarray(b.reshape(b.shape[0], -1), dtype=self._upper.dtype)
        x = self._owner.call(self._upper, bf, 33)
        return x.reshape(b.shape).astype(np.float64, copy=False)


class _PardisoSolver(SparseSolver):
    """MKL PARDISO through pypardiso's ctypes binding, symmetric positive definite mode on the upper triangle.

    One numeric factor lives in the solver at a time (older Factorization objects refuse to solve). With
    ``precision="single"`` the factorization and solves run in float32 (less time and memory; solutions accurate to
    about single precision times the condition number: meant as a preconditioner, see :mod:`offline.fem.krylov`).
    """

    backend = "pardiso"

    _template = None  # pypardiso searches the whole environment for libmkl_rt on every construction: do it once

    def __init__(self, precision: str = "double") -> None:
        import copy

        import pypardiso

        if _PardisoSolver._template is None:
            _PardisoSolver._template = pypardiso.PyPardisoSolver(mtype=2)
        self._ps = copy.copy(_PardisoSolver._template)
        self.precision = precision
        self._dtype = np.float32 if precision == "single" else np.float64
        self._upper_cache = None
        self.generation = 0
        self._fresh_state()

    def _fresh_state(self) -> None:
        """A fresh PARDISO handle and parameters for this solver; the next factor() analyzes anew."""
        self._ps.pt = np.zeros_like(self._ps.pt)
        self._ps.iparm = np.zeros_like(self._ps.iparm)
        self._ps.perm = np.zeros_like(self._ps.perm)
        self._ps.set_iparm(1, 2)
        # iparm(28): single-precision factorization; the matrix, right-hand sides and solutions are then float32
        self._ps.iparm[27] = 1 if self.precision == "single" else 0
        self._analyzed_key = None

    def call(self, upper: sp.csr_matrix, b: np.ndarray, phase: int) -> np.ndarray:
        from pypardiso.pardiso_wrapper import PyPardisoError

        self._ps.set_phase(phase)
        try:
            return self._ps._call_pardiso(upper, b)
        except PyPardisoError as exc:
            if exc.value in (-4,):
                raise NotPositiveDefinite(f"PARDISO error {exc.value} (zero or negative pivot)") from exc
            raise

    def _upper(self, A: sp.spmatrix) -> sp.csr_matrix:
        """Upper triangle of A as CSR; the entry selection is cached for A's sparsity pattern."""
        A = sp.csr_matrix(A)
        A.sort_indices()
        cache = self._upper_cache
        if cache is None or cache[0].shape != A.indptr.shape or not (
                np.array_equal(cache[0], A.indptr) and np.array_equal(cache[1], A.indices)):
            rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
            keep = np.flatnonzero(A.indices >= rows)
            counts = np.bincount(rows[keep], minlength=A.shape[0])
            indptr = np.concatenate([[0], np.cumsum(counts)]).astype(A.indptr.dtype)
            cache = (A.indptr.copy(), A.indices.copy(), keep, indptr, A.indices[keep].copy())
            self._upper_cache = cache
        _, _, keep, indptr, indices = cache
        return sp.csr_matrix((A.data[keep].astype(self._dtype, copy=False), indices, indptr), shape=A.shape)

    def factor(self, A: sp.spmatrix) -> Factorization:
        upper = self._upper(A)
        key = (upper.shape, upper.nnz)
        b = np.zeros((upper.shape[0], 1), order="F", dtype=self._dtype)
        if key != self._analyzed_key:
            self.call(upper, b, 11)
            self._analyzed_key = key
        # mtype 2 (SPD): a non-positive pivot ends phase 22 with error -4 and iparm(30) naming the equation;
        # PARDISO does not clear iparm(30) on success, so reset it before each factorization.
        self._ps.iparm[29] = 0
        try:
            self.call(upper, b, 22)
        except Exception:
            # A failed numeric phase leaves PARDISO's internal state unusable (even a later positive definite
            # matrix is refused): release it and start from a fresh handle and analysis next time.
            self._reset()
            raise
        self.generation += 1
        return _PardisoFactorization(self, upper, self.generation)

    def _reset(self) -> None:
        with contextlib.suppress(Exception):
            self._ps.free_memory(everything=True)
        self._fresh_state()
        self.generation += 1  # factorizations from before the failure must not solve with the new state

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self._ps.free_memory(everything=True)


# --------------------------------------------------------------------------------------------------- SuperLU
class _SuperLUFactorization(Factorization):
    backend = "superlu"

    def __init__(self, lu) -> None:
        self._lu = lu

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(np.asarray(b, dtype=np.float64))


class _SuperLUSolver(SparseSolver):
    """SciPy SuperLU (LU with a symmetric-mode ordering); cannot detect indefiniteness itself."""

    backend = "superlu"

    def factor(self, A: sp.spmatrix) -> Factorization:
        try:
            lu = spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
        except RuntimeError as exc:  # exactly singular
            raise NotPositiveDefinite(f"SuperLU: {exc}") from exc
        return _SuperLUFactorization(lu)


PRECISIONS = ("double", "single")


def make_solver(backend: str = "auto", precision: str = "double") -> SparseSolver:
    """A new solver for ``backend`` (``auto``, ``cholmod``, ``pardiso`` or ``superlu``).

    ``precision="single"`` asks for a float32 factorization (a preconditioner, not an exact solver); only PARDISO
    offers one, the other backends factor in double precision. ``solver.precision`` says which one was made.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"unknown factorization precision {precision!r}; choose one of {PRECISIONS}")
    name = resolve_backend(backend)
    if name == "cholmod":
        return _CholmodSolver()
    if name == "pardiso":
        return _PardisoSolver(precision)
    return _SuperLUSolver()


def factorize(A: sp.spmatrix, backend: str = "auto") -> Factorization:
    """One-off factorization of symmetric positive definite A."""
    return make_solver(backend).factor(A)
