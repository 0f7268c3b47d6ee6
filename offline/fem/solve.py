"""Quasi-static equilibrium of a hyperelastic tet mesh under Dirichlet conditions and gravity (Newton's method).

:func:`solve_static` minimises W(x) − f_ext·x over the free nodes with the constrained nodes moved to their targets.
The boundary motion (and gravity) is applied in load steps. The first Newton iteration of a step puts the constrained
nodes exactly on the step's targets and predicts the free nodes through K_fc (a linearised extension of the boundary
increment); the backtracking line search scales only the free part, keeping every element's J > 0, so from then on
each iteration is Newton on the free DoFs with a fixed boundary and Armijo decrease of the total energy. If no free
step lets the boundary increment in without inverting an element, the load step is halved. Element
Hessians are projected to PSD only when the factorization reports an indefinite matrix or the Newton direction is
not a descent direction. The symbolic factorization is reused across iterations; on failure the load step is
halved (and grows back after a success); after ``max_load_step_halvings`` successive halvings a
:class:`NotConverged` is raised with the last state saved to disk.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np
import scipy.sparse as sp

from . import energy as _en
from .krylov import pcg
from .linsolve import Factorization, NotPositiveDefinite, SparseSolver, make_solver, resolve_backend
from .materials import Material
from .mesh import TetMesh

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
    factorization only as a CG preconditioner, also right after it is made.
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
        if self.gravity is not None and np.asarray(self.gravity).shape != (3,):
            raise ValueError(f"SolverOptions.gravity must be a 3-vector or None, got {self.gravity!r}")


@dataclass(frozen=True, eq=False)
class StaticResult:
    """Outcome of :func:`solve_static`: positions, convergence, per-iteration log, phase timings (s), reactions (N).

    Each ``log`` entry holds step, iteration, energy (J), residual (N), alpha, projected (number of element
    Hessians projected to PSD), factor_s, tolerance (the residual threshold, N), factorized (whether the tangent was
    factored) and krylov (CG iterations spent on it). ``reactions`` follows ``dirichlet.nodes``; coordinates a node
    leaves free carry only the (converged, ≈ 0) residual there. ``factorizations`` counts numeric factorizations
    (failed ones included), ``krylov_iterations`` the CG iterations of the whole solve.
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


class _StepFailed(Exception):
    pass


#: Line-search halvings allowed in the iteration that moves the boundary in (smallest free-DoF scale 1/16).
_BOUNDARY_HALVINGS = 4
#: A load step has stalled after this many Newton steps in a row with a line-search scale below _STALL_ALPHA (a
#: nearly inverted state can take 100 such steps without progress; a smaller load step recovers sooner).
_STALL_ITERATIONS = 3
_STALL_ALPHA = 1e-4


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
    p = np.asarray(mesh.nodes)[np.asarray(mesh.tets)[:, :4]]
    from .mesh import QUADRATIC_EDGES

    return float(np.mean([np.linalg.norm(p[:, i] - p[:, j], axis=1).mean() for i, j in QUADRATIC_EDGES]))


def _reduced_selector(K: sp.csr_matrix, free: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
    """Indices into K.data of the free-free block, and that block's CSR skeleton."""
    tag = sp.csr_matrix((np.arange(1, K.nnz + 1, dtype=np.float64), K.indices, K.indptr), shape=K.shape)
    sub = tag[free][:, free].tocsr()
    sub.sort_indices()
    sel = sub.data.astype(np.int64) - 1
    return sel, sub


def _save_failure(directory: Path | None, mesh: TetMesh, x: np.ndarray, dirichlet: Dirichlet, lam: float,
                  log: list[dict]) -> Path | None:
    try:
        d = Path(directory) if directory is not None else Path(tempfile.gettempdir()) / "likeness_fem_failures"
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"not_converged_{time.strftime('%Y%m%dT%H%M%S')}_{uuid.uuid4().hex[:8]}.npz"
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, x=x, rest=np.asarray(mesh.nodes), tets=np.asarray(mesh.tets),
                            dirichlet_nodes=dirichlet.nodes, dirichlet_positions=dirichlet.positions,
                            load_factor=lam, residuals=np.array([r["residual"] for r in log]))
        os.replace(tmp, path)
        return path
    except OSError:
        return None


def solve_static(mesh: TetMesh, material: Material, dirichlet: Dirichlet, *, x0: np.ndarray | None = None,
                 options: SolverOptions = SolverOptions(), cache: FactorCache | None = None) -> StaticResult:
    """Equilibrium positions x = argmin W(x) − f_g·x subject to x[nodes] = positions (see module doc).

    ``cache``: a :class:`FactorCache` shared by successive solves on one mesh topology and constraint set (poses,
    design iterations) keeps the symbolic analysis and the last numeric factorization, which then preconditions
    the next solve (with ``options.reuse_factorization``).
    """
    t_total = time.perf_counter()
    opts = options
    resolve_backend(opts.backend)
    N = mesh.n_nodes
    nodes = dirichlet.nodes
    if nodes.size and nodes.max() >= N:
        raise ValueError(f"Dirichlet node index {nodes.max()} out of range for a mesh with {N} nodes")
    x = np.array(mesh.nodes if x0 is None else x0, dtype=np.float64)
    if x.shape != (N, 3):
        raise ValueError(f"x0 must have shape ({N}, 3), got {x.shape}")
    if _en.min_jacobian(mesh, x) <= 0:
        raise ValueError("initial positions invert at least one element (J <= 0)")
    cdofs = dirichlet.dofs
    free = np.ones(3 * N, dtype=bool)
    free[cdofs] = False
    free_idx = np.flatnonzero(free)
    if free_idx.size == 0:
        raise ValueError("every DoF is constrained; nothing to solve")
    if cdofs.size < 6:
        raise ValueError(f"only {cdofs.size} prescribed coordinates: at least 6 are needed to remove rigid motions")
    c_start = x.ravel()[cdofs].copy()
    c_goal = dirichlet.dof_values
    f_grav = (_en.gravity_forces(mesh, material, opts.gravity) if opts.gravity is not None else np.zeros((N, 3)))

    if opts.load_steps == "auto":
        disp = float(np.abs(c_goal - c_start).max()) if cdofs.size else 0.0
        n_steps = int(min(50, max(1, math.ceil(disp / _mean_edge_length(mesh)))))
    else:
        n_steps = int(opts.load_steps)

    if cache is None:
        cache = FactorCache()
    cache.bind(mesh, free_idx, opts.backend, opts.factor_precision)
    timings = {"assemble": 0.0, "factor": 0.0, "solve": 0.0, "krylov": 0.0, "line_search": 0.0, "total": 0.0}
    counts = {"factor": 0, "krylov": 0}
    log: list[dict] = []
    sel_cache: dict = {}
    iterations = 0

    def assemble_reduced(xc: np.ndarray, project: bool):
        t = time.perf_counter()
        K, n_proj = _en._stiffness(mesh, material, xc, project)
        if "sel" not in sel_cache:
            sel_cache["sel"], sel_cache["sub"] = _reduced_selector(K, free_idx)
        sub = sel_cache["sub"]
        Kff = sp.csr_matrix((K.data[sel_cache["sel"]], sub.indices, sub.indptr), shape=sub.shape)
        timings["assemble"] += time.perf_counter() - t
        return K, Kff, n_proj

    def potential(xc: np.ndarray, fext: np.ndarray) -> float:
        return _en.total_energy(mesh, material, xc) - float(np.sum(fext * xc))

    def newton(x_in: np.ndarray, lam: float, step: int) -> np.ndarray:
        nonlocal iterations
        xk = x_in.copy()
        tiny = 0
        e_known = None  # the potential at xk when the line search already evaluated it
        # the last step's target is the goal itself (c + 1.0 * (g - c) may differ from g by round-off)
        target = c_goal if lam >= 1.0 else c_start + lam * (c_goal - c_start)
        fext = lam * f_grav
        for it in range(opts.max_iterations):
            t = time.perf_counter()
            r = (_en.internal_forces(mesh, material, xk) - fext).ravel()
            timings["assemble"] += time.perf_counter() - t
            dc = target - xk.ravel()[cdofs]
            rf = r[free_idx]
            res = float(np.linalg.norm(rf))
            f_ref = max(float(np.linalg.norm(fext)), float(np.linalg.norm(r[cdofs])) if cdofs.size else 0.0)
            boundary_done = not np.any(dc)
            t = time.perf_counter()
            e_now = potential(xk, fext) if e_known is None else e_known  # the line search's reference value
            timings["line_search"] += time.perf_counter() - t
            if boundary_done and res <= opts.tol_force * max(1.0, f_ref):
                log.append({"step": step, "iteration": it, "energy": e_now, "residual": res, "alpha": 0.0,
                            "projected": 0, "factor_s": 0.0, "tolerance": opts.tol_force * max(1.0, f_ref),
                            "factorized": False, "krylov": 0})
                if opts.verbose:
                    print(f"  step {step} it {it}: converged |r|={res:.3e} (ref {f_ref:.3e})")
                return xk
            project = False
            direct = not opts.reuse_factorization
            factor_s, n_kry, factored = 0.0, 0, False
            while True:
                K, Kff, n_proj = assemble_reduced(xk, project)
                rhs = -rf
                if not boundary_done:
                    dfull = np.zeros(3 * N)
                    dfull[cdofs] = dc
                    rhs = rhs - (K @ dfull)[free_idx]
                du = None
                # forcing term ∝ the residual keeps Newton's quadratic convergence (and the final state as
                # accurate as an exact Newton step leaves it)
                rtol = max(1e-14, min(opts.krylov_rtol, res / max(1.0, f_ref)))
                if not direct and not project and cache.factorization is not None:
                    t = time.perf_counter()
                    kr = pcg(Kff, rhs, cache.factorization.solve, rtol, opts.krylov_max_iterations)
                    timings["krylov"] += time.perf_counter() - t
                    n_kry += kr.iterations
                    counts["krylov"] += kr.iterations
                    du = kr.x
                    direct = True  # if this direction is refused, factor the current tangent
                if du is None:
                    t = time.perf_counter()
                    counts["factor"] += 1
                    try:
                        fac = cache.solver.factor(Kff)
                    except NotPositiveDefinite:
                        cache.factorization = None  # the backend's state was reset
                        timings["factor"] += time.perf_counter() - t
                        if project:
                            raise _StepFailed("projected stiffness still not positive definite") from None
                        project = True
                        continue
                    cache.factorization = fac
                    factored = True
                    factor_s = time.perf_counter() - t
                    timings["factor"] += factor_s
                    t = time.perf_counter()
                    if cache.solver.precision == "single":  # a preconditioner, not an exact solve
                        kr = pcg(Kff, rhs, fac.solve, rtol, opts.krylov_max_iterations)
                        n_kry += kr.iterations
                        counts["krylov"] += kr.iterations
                        du = np.full(rhs.shape, np.nan) if kr.x is None else kr.x
                    else:
                        du = fac.solve(rhs)
                    timings["solve"] += time.perf_counter() - t
                if not np.all(np.isfinite(du)):
                    if project:
                        raise _StepFailed("non-finite Newton direction")
                    project = project or factored
                    direct = True
                    continue
                slope = float(rf @ du)
                if boundary_done and slope >= 0.0:
                    if project:
                        raise _StepFailed("no descent direction even with PSD projection")
                    project = project or factored
                    direct = True
                    continue
                break
            d = np.zeros(3 * N)
            d[free_idx] = du
            d = d.reshape(N, 3)
            # The boundary goes all the way to this step's target at once; only the free DoFs are scaled by the
            # line search, so after one iteration every step is plain Newton on the free DoFs with a fixed
            # boundary and monotone (Armijo) energy decrease. A boundary increment that no free-DoF step can
            # follow without inverting an element fails the load step, which is then halved.
            base = xk.copy()
            base.reshape(-1)[cdofs] = target
            t = time.perf_counter()
            alpha = 1.0
            accepted = False
            # While the boundary moves in, the free DoFs must take a fair share of the predicted step: a start
            # with the boundary in place and the free nodes barely moved is nearly inverted (forces of 1e9 N and
            # more were seen) and Newton stalls from there, so a smaller load step is the better answer.
            for _ in range(30 if boundary_done else _BOUNDARY_HALVINGS + 1):
                xt = base + alpha * d
                e_t = _en.total_energy(mesh, material, xt)
                if np.isfinite(e_t):
                    if not boundary_done:
                        accepted = True
                        break
                    e_t -= float(np.sum(fext * xt))
                    if e_t <= e_now + opts.armijo * alpha * slope:
                        accepted = True
                        break
                    # Near convergence energy differences drown in round-off: accept a full step that reduces r.
                    if alpha == 1.0 and abs(e_t - e_now) <= 1e-12 * max(1.0, abs(e_now)):
                        r_t = (_en.internal_forces(mesh, material, xt) - fext).ravel()[free_idx]
                        if np.linalg.norm(r_t) < res:
                            accepted = True
                            break
                alpha *= 0.5
            timings["line_search"] += time.perf_counter() - t
            iterations += 1
            log.append({"step": step, "iteration": it, "energy": e_now, "residual": res,
                        "alpha": alpha if accepted else 0.0, "projected": int(n_proj), "factor_s": factor_s,
                        "tolerance": opts.tol_force * max(1.0, f_ref), "factorized": factored, "krylov": n_kry})
            if opts.verbose:
                print(f"  step {step} it {it}: |r|={res:.3e} (ref {f_ref:.3e}) E={e_now:.6e} alpha={alpha:.3g} "
                      f"projected={n_proj} factor={factor_s:.3f}s cg={n_kry}")
            if not accepted:
                raise _StepFailed("line search found no admissible step")
            tiny = tiny + 1 if boundary_done and alpha < _STALL_ALPHA else 0
            if tiny >= _STALL_ITERATIONS:
                raise _StepFailed(f"Newton stalled ({tiny} steps in a row with alpha < {_STALL_ALPHA:g})")
            xk = xt
            e_known = e_t if boundary_done else e_t - float(np.sum(fext * xt))
        raise _StepFailed(f"no convergence in {opts.max_iterations} iterations")

    dlam0 = 1.0 / n_steps
    lam, dlam, halvings, steps_done = 0.0, dlam0, 0, 0
    state_lam = 0.0
    while lam < 1.0 - 1e-12:
        lam1 = min(1.0, lam + dlam)
        if 1.0 - lam1 < 1e-9:
            lam1 = 1.0
        try:
            x = newton(x, lam1, steps_done)
            lam, state_lam = lam1, lam1
            steps_done += 1
            # a step that went through lets the next one grow back towards the planned size
            halvings, dlam = 0, min(dlam0, 2.0 * dlam)
        except _StepFailed as exc:
            halvings += 1
            if opts.verbose:
                print(f"  load step to {lam1:.4f} failed ({exc}); halving")
            if halvings > opts.max_load_step_halvings:
                timings["total"] = time.perf_counter() - t_total
                result = StaticResult(x, False, iterations, steps_done, tuple(log), MappingProxyType(dict(timings)),
                                      _reactions(mesh, material, x, nodes, f_grav * state_lam), counts["factor"],
                                      counts["krylov"])
                path = _save_failure(opts.failure_dir, mesh, x, dirichlet, state_lam, log)
                raise NotConverged(f"solve_static: {exc} at load factor {lam1:.4f} after {halvings - 1} successive "
                                   "halvings",
                                   result, path) from None
            dlam *= 0.5
    timings["total"] = time.perf_counter() - t_total
    return StaticResult(x, True, iterations, steps_done, tuple(log), MappingProxyType(dict(timings)),
                        _reactions(mesh, material, x, nodes, f_grav), counts["factor"], counts["krylov"])


def _reactions(mesh: TetMesh, material: Material, x: np.ndarray, nodes: np.ndarray, fext: np.ndarray) -> np.ndarray:
    """Constraint force at each Dirichlet node: internal force there minus the external load (K, 3)."""
    f = _en.internal_forces(mesh, material, x)
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
    K = _en.stiffness(mesh, material, x, project_psd=project_psd)
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
