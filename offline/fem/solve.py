"""Quasi-static equilibrium of a hyperelastic tet mesh under Dirichlet conditions and gravity (Newton's method).

:func:`solve_static` minimises W(x) − f_ext·x over the free nodes with the constrained nodes moved to their targets.
The boundary motion (and gravity) is applied in load steps. The first Newton iteration of a step puts the constrained
nodes exactly on the step's targets and predicts the free nodes through K_fc (a linearised extension of the boundary
increment); the backtracking line search scales only the free part, keeping every element's J > 0, so from then on
each iteration is Newton on the free DoFs with a fixed boundary and Armijo decrease of the total energy. If no free
step lets the boundary increment in without inverting an element, the load step is halved. The tangent is made
positive semidefinite (each quadrature point's material tangent projected) only when the factorization reports an
indefinite matrix or the Newton direction is not a descent direction, and stays so while the projected steps are cut
short by the line search. The symbolic factorization is reused across iterations; on failure the load step is
halved (and grows back after a success); after ``max_load_step_halvings`` successive halvings a
:class:`NotConverged` is raised with the last state saved to disk. Here: the boundary conditions, the options and
result, the load stepping; one load step's Newton iterations are :mod:`offline.fem.newton`.
"""

from __future__ import annotations

import hashlib
import math
import tempfile
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np
import scipy.sparse as sp

from models.atomic import atomic_path

from .energy import gravity_forces, internal_forces, min_jacobian, stiffness
from .linsolve import Factorization, SparseSolver, make_solver, resolve_backend
from .materials import Material
from .mesh import QUADRATIC_EDGES, TetMesh
from .newton import NewtonProblem, NewtonWork, StepFailed, solve_load_step

# ------------------------------------------------------------------------------------------------ boundary data


@dataclass(frozen=True, eq=False)
class Dirichlet:
    """Prescribed positions: node indices (K,) and their target positions (K, 3) in metres.

    ``components`` (K, 3) bool, optional: which coordinates of each node are prescribed (default: all three);
    unprescribed coordinates are free (e.g. frictionless contact constrains only the normal one).
    """

    nodes: np.ndarray
    positions: np.ndarray
    components: np.ndarray | None = None

    def __post_init__(self) -> None:
        nodes = np.asarray(self.nodes, dtype=np.int64).reshape(-1)
        pos = np.asarray(self.positions, dtype=np.float64)
        if pos.shape != (nodes.size, 3):
            raise ValueError(f"Dirichlet.positions must have shape ({nodes.size}, 3), got {pos.shape}")
        if np.unique(nodes).size != nodes.size:
            raise ValueError("Dirichlet.nodes contains duplicate node indices (use combine() to merge)")
        if nodes.size and nodes.min() < 0:
            raise ValueError(f"Dirichlet.nodes contains a negative index ({nodes.min()})")
        if not np.all(np.isfinite(pos)):
            raise ValueError("Dirichlet.positions contains non-finite values")
        comp = np.ones((nodes.size, 3), dtype=bool) if self.components is None else np.asarray(self.components)
        if comp.shape != (nodes.size, 3) or comp.dtype != np.bool_:
            raise ValueError(f"Dirichlet.components must be a bool array of shape ({nodes.size}, 3), "
                             f"got {comp.dtype} {comp.shape}")
        for name, arr in (("nodes", nodes), ("positions", pos), ("components", comp)):
            arr = np.ascontiguousarray(arr)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def dofs(self) -> np.ndarray:
        """Prescribed DoF indices (3 * node + axis), in node order."""
        return (3 * self.nodes[:, None] + np.arange(3))[self.components]

    @property
    def dof_values(self) -> np.ndarray:
        """Prescribed coordinate of each entry of :attr:`dofs`."""
        return self.positions[self.components]


def _set_nodes(mesh: TetMesh, name: str) -> np.ndarray:
    if name not in mesh.node_sets:
        raise KeyError(f"mesh has no node set {name!r} (known: {sorted(mesh.node_sets)})")
    return np.asarray(mesh.node_sets[name])


def fixed(mesh: TetMesh, set_names: str | Sequence[str]) -> Dirichlet:
    """Nodes of the named set(s) held at their rest positions."""
    names = [set_names] if isinstance(set_names, str) else list(set_names)
    nodes = np.unique(np.concatenate([_set_nodes(mesh, n) for n in names])) if names else np.zeros(0, np.int64)
    return Dirichlet(nodes, np.asarray(mesh.nodes)[nodes])


def combine(*conditions: Dirichlet) -> Dirichlet:
    """Union of Dirichlet conditions; a node given several times keeps its first entry (target and components)."""
    if not conditions:
        return Dirichlet(np.zeros(0, np.int64), np.zeros((0, 3)))
    nodes = np.concatenate([c.nodes for c in conditions])
    pos = np.concatenate([c.positions for c in conditions])
    comp = np.concatenate([c.components for c in conditions])
    _, first = np.unique(nodes, return_index=True)
    return Dirichlet(nodes[first], pos[first], comp[first])


def rigid_transform_dirichlet(mesh: TetMesh, transforms: Mapping[str, np.ndarray],
                              fixed_sets: Sequence[str] = ()) -> Dirichlet:
    """Each named node set moved rigidly by its 4x4 homogeneous transform (applied to rest positions).

    A node in several moved sets follows the first in the mapping's order; nodes of ``fixed_sets`` not in any moved
    set stay at rest.
    """
    parts = []
    for name, T in transforms.items():
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"transform for node set {name!r} must be 4x4, got shape {T.shape}")
        R = T[:3, :3]
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1])):
            raise ValueError(f"transform for node set {name!r} is not a rigid motion (rotation + translation)")
        idx = _set_nodes(mesh, name)
        X = np.asarray(mesh.nodes)[idx]
        parts.append(Dirichlet(idx, X @ T[:3, :3].T + T[:3, 3]))
    if fixed_sets:
        parts.append(fixed(mesh, list(fixed_sets)))
    return combine(*parts)


# ------------------------------------------------------------------------------------------------ options, result


@dataclass(frozen=True)
class SolverOptions:
    """Newton solver settings.

    ``backend``: linear solver (``auto``, ``cholmod``, ``pardiso``, ``superlu``). ``tol_force``: converged when
    ‖r_free‖ <= tol_force · max(1, ‖f_ref‖) with f_ref the larger of the external load and the reactions (N).
    ``load_steps``: number of equal load increments, or ``"auto"`` (one step per mean element edge length of the
    largest boundary displacement). ``gravity``: acceleration vector (m/s²) or None. ``failure_dir``: where the
    state of a failed solve is saved (default: the system temp dir).

    ``reuse_factorization`` (inexact Newton): each Newton system is first solved by conjugate gradients
    preconditioned with the most recent numeric factorization (of an earlier tangent, possibly of an earlier load
    step or, through a :class:`FactorCache`, an earlier solve), to a relative residual min(``krylov_rtol``, ‖r‖ / f_ref)
    (a forcing term that shrinks with the residual keeps Newton's quadratic convergence); the current
    tangent is factored only when CG needs more than ``krylov_max_iterations`` back-substitutions or meets
    non-positive curvature. The convergence test on the force residual is the same either way.
    ``factor_precision="single"`` (PARDISO only, with ``reuse_factorization``) factors in float32 and uses every
    factorization only as a CG preconditioner, also right after it is made. ``psd_projection``: how an indefinite
    tangent is made positive semidefinite (``"quadrature"``: each quadrature point's material tangent, the default;
    ``"element"``: each element Hessian, slower; see :func:`~offline.fem.energy.stiffness`).
    """

    backend: str = "auto"
    tol_force: float = 1e-6
    max_iterations: int = 30
    load_steps: int | str = 1
    max_load_step_halvings: int = 6
    armijo: float = 1e-4
    gravity: tuple[float, float, float] | None = None
    verbose: bool = False
    failure_dir: Path | None = None
    reuse_factorization: bool = True
    krylov_rtol: float = 0.1
    krylov_max_iterations: int = 12
    factor_precision: str = "double"
    psd_projection: str = "quadrature"

    def __post_init__(self) -> None:
        if not (self.tol_force > 0):
            raise ValueError(f"SolverOptions.tol_force must be > 0, got {self.tol_force}")
        if self.max_iterations < 1:
            raise ValueError(f"SolverOptions.max_iterations must be >= 1, got {self.max_iterations}")
        if self.load_steps != "auto" and (not isinstance(self.load_steps, int | np.integer) or self.load_steps < 1):
            raise ValueError(f"SolverOptions.load_steps must be an int >= 1 or 'auto', got {self.load_steps!r}")
        if self.max_load_step_halvings < 0:
            raise ValueError("SolverOptions.max_load_step_halvings must be >= 0")
        if not (0 < self.armijo < 1):
            raise ValueError(f"SolverOptions.armijo must be in (0, 1), got {self.armijo}")
        if not (0 < self.krylov_rtol < 1):
            raise ValueError(f"SolverOptions.krylov_rtol must be in (0, 1), got {self.krylov_rtol}")
        if self.krylov_max_iterations < 1:
            raise ValueError(f"SolverOptions.krylov_max_iterations must be >= 1, got {self.krylov_max_iterations}")
        if self.factor_precision not in ("double", "single"):
            raise ValueError(f"SolverOptions.factor_precision must be 'double' or 'single', "
                             f"got {self.factor_precision!r}")
        if self.factor_precision == "single" and not self.reuse_factorization:
            raise ValueError("SolverOptions.factor_precision='single' needs reuse_factorization=True "
                             "(a float32 factorization is used only as a preconditioner)")
        if self.psd_projection not in ("quadrature", "element"):
            raise ValueError(f"SolverOptions.psd_projection must be 'quadrature' or 'element', "
                             f"got {self.psd_projection!r}")
        if self.gravity is not None and np.asarray(self.gravity).shape != (3,):
            raise ValueError(f"SolverOptions.gravity must be a 3-vector or None, got {self.gravity!r}")


@dataclass(frozen=True, eq=False)
class StaticResult:
    """Outcome of :func:`solve_static`: positions, convergence, per-iteration log, phase timings (s), reactions (N).

    Each ``log`` entry holds step, iteration, energy (J), residual (N), alpha, projected (number of elements
    with a material tangent projected to PSD), factor_s, tolerance (the residual threshold, N), factorized
    (whether the tangent was factored) and krylov (CG iterations spent on it). ``reactions`` follows
    ``dirichlet.nodes``; coordinates a node leaves free carry only the (converged, ≈ 0) residual there.
    ``factorizations`` counts numeric factorizations (failed ones included), ``krylov_iterations`` the CG
    iterations of the whole solve.
    """

    x: np.ndarray
    converged: bool
    iterations: int
    load_steps: int
    log: tuple[dict, ...] = ()
    timings: Mapping[str, float] = field(default_factory=dict)
    reactions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    factorizations: int = 0
    krylov_iterations: int = 0

    def __reduce__(self):
        return (StaticResult, (self.x, self.converged, self.iterations, self.load_steps, self.log,
                               dict(self.timings), self.reactions, self.factorizations, self.krylov_iterations))

    def reaction_total(self) -> np.ndarray:
        """Sum of the constraint forces over all Dirichlet nodes (3,)."""
        return np.asarray(self.reactions).sum(axis=0)


class NotConverged(RuntimeError):
    """Newton failed after the allowed load-step halvings; ``result`` is the last state, saved at ``state_path``."""

    def __init__(self, message: str, result: StaticResult, state_path: Path | None) -> None:
        super().__init__(f"{message} (state saved to {state_path})")
        self.result = result
        self.state_path = state_path


# ------------------------------------------------------------------------------------------------ solver


class FactorCache:
    """A sparse solver and its last numeric factorization, kept between :func:`solve_static` calls.

    Bound to one mesh topology, set of constrained DoFs and backend; binding to another discards the contents
    (rest positions may change: a factorization for a nearby rest shape still preconditions well).
    """

    def __init__(self) -> None:
        self._key: tuple | None = None
        self.solver: SparseSolver | None = None
        self.factorization: Factorization | None = None

    def bind(self, mesh: TetMesh, free_idx: np.ndarray, backend: str, precision: str = "double") -> None:
        """Use this cache for ``mesh``'s topology with free DoFs ``free_idx``; reset it if that differs."""
        tets = np.ascontiguousarray(mesh.tets)
        key = (resolve_backend(backend), precision, mesh.n_nodes, tets.shape, hashlib.sha1(tets.data).hexdigest(),
               hashlib.sha1(np.ascontiguousarray(free_idx, dtype=np.int64).data).hexdigest())
        if key != self._key:
            self._key = key
            self.solver = make_solver(backend, precision)
            self.factorization = None


def _mean_edge_length(mesh: TetMesh) -> float:
    """Mean length of the corner tets' edges (m): the scale of ``load_steps="auto"``."""
    p = np.asarray(mesh.nodes)[np.asarray(mesh.tets)[:, :4]]
    return float(np.mean([np.linalg.norm(p[:, i] - p[:, j], axis=1).mean() for i, j in QUADRATIC_EDGES]))


def _save_failure(directory: Path | None, mesh: TetMesh, x: np.ndarray, dirichlet: Dirichlet, lam: float,
                  log: list[dict]) -> Path | None:
    """Save the state of a failed solve as ``.npz`` in ``directory`` (default: the temp dir); None if it cannot."""
    try:
        d = Path(directory) if directory is not None else Path(tempfile.gettempdir()) / "likeness_fem_failures"
        path = d / f"not_converged_{time.strftime('%Y%m%dT%H%M%S')}_{uuid.uuid4().hex[:8]}.npz"
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(tmp, x=x, rest=np.asarray(mesh.nodes), tets=np.asarray(mesh.tets),
                                dirichlet_nodes=dirichlet.nodes, dirichlet_positions=dirichlet.positions,
                                load_factor=lam, residuals=np.array([r["residual"] for r in log]))
        return path
    except OSError:
        return None


def _problem(mesh: TetMesh, material: Material, dirichlet: Dirichlet, x0: np.ndarray | None, opts: SolverOptions,
             cache: FactorCache | None) -> tuple[NewtonProblem, np.ndarray]:
    """Check the inputs and gather the solve's constants; returns them and the starting positions (N, 3)."""
    resolve_backend(opts.backend)
    N = mesh.n_nodes
    nodes = dirichlet.nodes
    if nodes.size and nodes.max() >= N:
        raise ValueError(f"Dirichlet node index {nodes.max()} out of range for a mesh with {N} nodes")
    x = np.array(mesh.nodes if x0 is None else x0, dtype=np.float64)
    if x.shape != (N, 3):
        raise ValueError(f"x0 must have shape ({N}, 3), got {x.shape}")
    if min_jacobian(mesh, x) <= 0:
        raise ValueError("initial positions invert at least one element (J <= 0)")
    cdofs = dirichlet.dofs
    free = np.ones(3 * N, dtype=bool)
    free[cdofs] = False
    free_idx = np.flatnonzero(free)
    if free_idx.size == 0:
        raise ValueError("every DoF is constrained; nothing to solve")
    if cdofs.size < 6:
        raise ValueError(f"only {cdofs.size} prescribed coordinates: at least 6 are needed to remove rigid motions")
    f_grav = (gravity_forces(mesh, material, opts.gravity) if opts.gravity is not None else np.zeros((N, 3)))
    cache = FactorCache() if cache is None else cache
    problem = NewtonProblem(mesh, material, dirichlet, opts, cache, cdofs, free_idx, x.ravel()[cdofs].copy(),
                       dirichlet.dof_values, f_grav)
    return problem, x


def _load_step_count(p: NewtonProblem) -> int:
    """The planned number of load steps: the option, or for ``"auto"`` one per mean edge length of boundary travel."""
    if p.opts.load_steps != "auto":
        return int(p.opts.load_steps)
    disp = float(np.abs(p.c_goal - p.c_start).max()) if p.cdofs.size else 0.0
    return int(min(50, max(1, math.ceil(disp / _mean_edge_length(p.mesh)))))


def solve_static(mesh: TetMesh, material: Material, dirichlet: Dirichlet, *, x0: np.ndarray | None = None,
                 options: SolverOptions = SolverOptions(), cache: FactorCache | None = None) -> StaticResult:
    """Equilibrium positions x = argmin W(x) − f_g·x subject to x[nodes] = positions (see module doc).

    ``cache``: a :class:`FactorCache` shared by successive solves on one mesh topology and constraint set (poses,
    design iterations) keeps the symbolic analysis and the last numeric factorization, which then preconditions
    the next solve (with ``options.reuse_factorization``).
    """
    t_total = time.perf_counter()
    p, x = _problem(mesh, material, dirichlet, x0, options, cache)
    n_steps = _load_step_count(p)
    p.cache.bind(mesh, p.free_idx, options.backend, options.factor_precision)
    w = NewtonWork()
    x, steps_done = _load_stepping(p, w, x, n_steps, t_total)
    return _result(p, w, x, True, steps_done, 1.0, t_total)


def _result(p: NewtonProblem, w: NewtonWork, x: np.ndarray, converged: bool, steps_done: int, lam: float,
            t_total: float) -> StaticResult:
    """The :class:`StaticResult` of the state ``x`` reached at load factor ``lam``."""
    w.timings["total"] = time.perf_counter() - t_total
    fext = p.f_grav if converged else p.f_grav * lam
    return StaticResult(x, converged, w.iterations, steps_done, tuple(w.log), MappingProxyType(dict(w.timings)),
                        _reactions(p.mesh, p.material, x, p.dirichlet.nodes, fext), w.factorizations,
                        w.krylov_iterations)


def _load_stepping(p: NewtonProblem, w: NewtonWork, x: np.ndarray, n_steps: int, t_total: float
                   ) -> tuple[np.ndarray, int]:
    """Apply the load in steps of planned size 1/n_steps from ``x``: a failed step is halved (and the step size
    grows back after a success); returns the equilibrium at full load and the number of steps taken.

    Raises :class:`NotConverged` (with the last state saved) after ``max_load_step_halvings`` halvings in a row.
    """
    opts = p.opts
    dlam0 = 1.0 / n_steps
    lam, dlam, halvings, steps_done = 0.0, dlam0, 0, 0
    while lam < 1.0 - 1e-12:
        lam1 = min(1.0, lam + dlam)
        if 1.0 - lam1 < 1e-9:
            lam1 = 1.0
        try:
            x = solve_load_step(p, w, x, lam1, steps_done)
        except StepFailed as exc:
            halvings += 1
            if opts.verbose:
                print(f"  load step to {lam1:.4f} failed ({exc}); halving")
            if halvings > opts.max_load_step_halvings:
                result = _result(p, w, x, False, steps_done, lam, t_total)
                path = _save_failure(opts.failure_dir, p.mesh, x, p.dirichlet, lam, w.log)
                raise NotConverged(f"solve_static: {exc} at load factor {lam1:.4f} after {halvings - 1} successive "
                                   "halvings", result, path) from None
            dlam *= 0.5
            continue
        lam = lam1
        steps_done += 1
        # a step that went through lets the next one grow back towards the planned size
        halvings, dlam = 0, min(dlam0, 2.0 * dlam)
    return x, steps_done


def _reactions(mesh: TetMesh, material: Material, x: np.ndarray, nodes: np.ndarray, fext: np.ndarray) -> np.ndarray:
    """Constraint force at each Dirichlet node: internal force there minus the external load (K, 3)."""
    f = internal_forces(mesh, material, x)
    return (f - fext)[nodes]


def tangent_factorization(mesh: TetMesh, material: Material, x: np.ndarray, dirichlet: Dirichlet, *,
                          backend: str = "auto", project_psd: bool = False, cache: FactorCache | None = None
                          ) -> tuple[Factorization, np.ndarray, sp.csr_matrix]:
    """Factor the free-free block K_ff of the tangent stiffness at ``x`` for adjoint and sensitivity solves.

    Returns (factorization, free DoF indices, full stiffness K). At an equilibrium, the change of the free DoFs for a
    change δc of the prescribed coordinates is δu_f = −K_ff⁻¹ K_fc δc, and an adjoint λ = K_ff⁻¹ ∂q/∂u_f gives
    dq/dp = −λᵀ ∂r_f/∂p for any parameter p. With a double-precision ``cache`` (the one the forward solves use) the
    symbolic analysis is reused and the new factorization becomes the cache's preconditioner for the next solve;
    with PARDISO this invalidates the cache's previous factorization object.
    """
    K = stiffness(mesh, material, x, project_psd=project_psd)
    free = np.ones(3 * mesh.n_nodes, dtype=bool)
    free[dirichlet.dofs] = False
    free_idx = np.flatnonzero(free)
    Kff = K[free_idx][:, free_idx].tocsr()
    if cache is None:
        return make_solver(backend).factor(Kff), free_idx, K
    cache.bind(mesh, free_idx, backend)
    cache.factorization = None
    fac = cache.solver.factor(Kff)
    cache.factorization = fac
    return fac, free_idx, K
