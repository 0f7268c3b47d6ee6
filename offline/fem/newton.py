"""One load step of :func:`offline.fem.solve.solve_static`: Newton's method on the free DoFs with a line search.

The first iteration of a step puts the constrained nodes on the step's targets and predicts the free nodes through
K_fc; after it every iteration is Newton on the free DoFs with a fixed boundary and Armijo decrease of the total
energy. Each iteration is: the residual and convergence test (:func:`_iterate`), a direction
(:func:`_newton_direction`: CG preconditioned by a cached factorization, or a new factorization, with PSD projection
as fallback), a backtracking line search (:func:`_line_search`) and a log entry. A step that cannot go on raises
:class:`StepFailed`; the caller halves it. The solve's constants are a frozen :class:`NewtonProblem`, what it
accumulates (timings, counters, log) a :class:`NewtonWork`, as a model and its data are kept apart.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from .energy import _stiffness, internal_forces, total_energy
from .krylov import pcg
from .linsolve import Factorization, NotPositiveDefinite
from .materials import Material
from .mesh import TetMesh

if TYPE_CHECKING:
    from .solve import Dirichlet, FactorCache, SolverOptions

class StepFailed(Exception):
    """A load step failed (no admissible line-search step, no descent, stall, no convergence): halve it."""


#: Line-search halvings allowed in the iteration that moves the boundary in (smallest free-DoF scale 1/16).
_BOUNDARY_HALVINGS = 4
#: A load step has stalled after this many Newton steps in a row with a line-search scale below _STALL_ALPHA (a
#: nearly inverted state can take 100 such steps without progress; a smaller load step recovers sooner).
_STALL_ITERATIONS = 3
_STALL_ALPHA = 1e-4


@dataclass(frozen=True, eq=False)
class NewtonProblem:
    """The constants of one :func:`~offline.fem.solve.solve_static` call: the model, the options and the boundary
    data in DoF form.

    ``cdofs``/``free_idx``: constrained and free DoF indices; ``c_start``/``c_goal``: the constrained coordinates
    at the start and at full load; ``f_grav``: the external load at full load (N, 3).
    """

    mesh: TetMesh
    material: Material
    dirichlet: Dirichlet
    opts: SolverOptions
    cache: FactorCache
    cdofs: np.ndarray
    free_idx: np.ndarray
    c_start: np.ndarray
    c_goal: np.ndarray
    f_grav: np.ndarray


@dataclass(eq=False)
class NewtonWork:
    """What one solve accumulates: phase timings, counters, the iteration log and the free-free CSR selector."""

    timings: dict[str, float] = field(default_factory=lambda: dict.fromkeys(
        ("assemble", "factor", "solve", "krylov", "line_search", "total"), 0.0))
    factorizations: int = 0
    krylov_iterations: int = 0
    iterations: int = 0
    log: list[dict] = field(default_factory=list)
    selector: tuple[np.ndarray, sp.csr_matrix] | None = None


@dataclass(frozen=True, eq=False)
class _Iterate:
    """The state at one Newton iterate of a load step: its load, residual and the line search's reference energy.

    ``target``: this step's constrained coordinates; ``fext``: its external load (N, 3); ``rf``: the free-DoF
    force residual and ``res`` its norm; ``f_ref``: the force scale of the convergence test; ``dc``: how far the
    constrained coordinates still are from ``target``; ``boundary_done``: whether they sit on it (then Newton runs on
    the free DoFs only); ``energy``: the potential at the iterate.
    """

    target: np.ndarray
    fext: np.ndarray
    rf: np.ndarray
    res: float
    f_ref: float
    dc: np.ndarray
    boundary_done: bool
    energy: float

    def tolerance(self, opts: SolverOptions) -> float:
        """The residual threshold of the convergence test (N)."""
        return opts.tol_force * max(1.0, self.f_ref)


@dataclass(frozen=True, eq=False)
class _Direction:
    """A Newton direction on the free DoFs and how it was found (projected elements, factorization, CG work)."""

    du: np.ndarray
    slope: float
    projected: int
    factor_s: float
    factored: bool
    krylov: int


@dataclass(frozen=True, eq=False)
class _Step:
    """The line search's outcome: the scale ``alpha``, the new positions ``x`` and their ``energy`` (W(x), less
    fext·x once the boundary is in; see :func:`_line_search`)."""

    accepted: bool
    alpha: float
    x: np.ndarray
    energy: float


def _reduced_selector(K: sp.csr_matrix, free: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
    """Indices into K.data of the free-free block, and that block's CSR skeleton."""
    tag = sp.csr_matrix((np.arange(1, K.nnz + 1, dtype=np.float64), K.indices, K.indptr), shape=K.shape)
    sub = tag[free][:, free].tocsr()
    sub.sort_indices()
    sel = sub.data.astype(np.int64) - 1
    return sel, sub


def solve_load_step(p: NewtonProblem, w: NewtonWork, x_in: np.ndarray, lam: float, step: int) -> np.ndarray:
    """Newton's method for the load step to load factor ``lam`` from ``x_in``; the equilibrium there, or
    :class:`StepFailed`.

    The first iteration moves the boundary all the way to this step's target; only the free DoFs are scaled by the
    line search, so after one iteration every step is plain Newton on the free DoFs with a fixed boundary and
    monotone (Armijo) energy decrease. A boundary increment that no free-DoF step can follow without inverting an
    element fails the load step.
    """
    opts = p.opts
    xk = x_in.copy()
    tiny = 0
    e_known = None  # the potential at xk when the line search already evaluated it
    indefinite = False  # the last direction needed PSD projection and its step was cut short
    # the last step's target is the goal itself (c + 1.0 * (g - c) may differ from g by round-off)
    target = p.c_goal if lam >= 1.0 else p.c_start + lam * (p.c_goal - p.c_start)
    fext = lam * p.f_grav
    for it in range(opts.max_iterations):
        state = _iterate(p, w, xk, target, fext, e_known)
        if state.boundary_done and state.res <= state.tolerance(opts):
            _log_converged(p, w, state, step, it)
            return xk
        direction = _newton_direction(p, w, xk, state, project=indefinite)
        trial = _line_search(p, w, xk, state, direction)
        w.iterations += 1
        _log_iteration(p, w, state, direction, trial, step, it)
        if not trial.accepted:
            raise StepFailed("line search found no admissible step")
        tiny = tiny + 1 if state.boundary_done and trial.alpha < _STALL_ALPHA else 0
        if tiny >= _STALL_ITERATIONS:
            raise StepFailed(f"Newton stalled ({tiny} steps in a row with alpha < {_STALL_ALPHA:g})")
        # far from equilibrium the tangent stays indefinite for many iterations: until a projected direction is
        # taken whole, start projected rather than factor an indefinite tangent first only to see it refused
        indefinite = direction.projected > 0 and trial.alpha < 1.0
        xk = trial.x
        e_known = trial.energy if state.boundary_done else trial.energy - float(np.sum(fext * trial.x))
    raise StepFailed(f"no convergence in {opts.max_iterations} iterations")


def _iterate(p: NewtonProblem, w: NewtonWork, xk: np.ndarray, target: np.ndarray, fext: np.ndarray,
             e_known: float | None) -> _Iterate:
    """The residual at ``xk`` and its potential (``e_known`` when the line search already evaluated it)."""
    t = time.perf_counter()
    r = (internal_forces(p.mesh, p.material, xk) - fext).ravel()
    w.timings["assemble"] += time.perf_counter() - t
    dc = target - xk.ravel()[p.cdofs]
    rf = r[p.free_idx]
    res = float(np.linalg.norm(rf))
    f_ref = max(float(np.linalg.norm(fext)), float(np.linalg.norm(r[p.cdofs])) if p.cdofs.size else 0.0)
    t = time.perf_counter()
    e_now = _potential(p, xk, fext) if e_known is None else e_known  # the line search's reference value
    w.timings["line_search"] += time.perf_counter() - t
    return _Iterate(target, fext, rf, res, f_ref, dc, not np.any(dc), e_now)


def _potential(p: NewtonProblem, x: np.ndarray, fext: np.ndarray) -> float:
    """Total potential energy W(x) − fext·x (J)."""
    return total_energy(p.mesh, p.material, x) - float(np.sum(fext * x))


def _assemble_reduced(p: NewtonProblem, w: NewtonWork, x: np.ndarray, project: bool
                      ) -> tuple[sp.csr_matrix, sp.csr_matrix, int]:
    """The tangent K at ``x``, its free-free block K_ff, and how many elements had a material tangent projected."""
    t = time.perf_counter()
    K, n_proj = _stiffness(p.mesh, p.material, x, p.opts.psd_projection if project else False)
    if w.selector is None:
        w.selector = _reduced_selector(K, p.free_idx)
    sel, sub = w.selector
    Kff = sp.csr_matrix((K.data[sel], sub.indices, sub.indptr), shape=sub.shape)
    w.timings["assemble"] += time.perf_counter() - t
    return K, Kff, n_proj


def _newton_rhs(p: NewtonProblem, K: sp.csr_matrix, state: _Iterate) -> np.ndarray:
    """Right-hand side of the free-DoF Newton system: −r_f, less K_fc times the boundary increment still to go."""
    rhs = -state.rf
    if not state.boundary_done:
        dfull = np.zeros(3 * p.mesh.n_nodes)
        dfull[p.cdofs] = state.dc
        rhs = rhs - (K @ dfull)[p.free_idx]
    return rhs


def _newton_direction(p: NewtonProblem, w: NewtonWork, xk: np.ndarray, state: _Iterate, *, project: bool = False
                      ) -> _Direction:
    """A Newton direction on the free DoFs: CG preconditioned by the cached factorization when allowed, else a new
    factorization; the tangent made PSD (:func:`~offline.fem.energy.stiffness` with ``project_psd``) when it is
    indefinite or the direction is refused, or from the start with ``project``."""
    direct = not p.opts.reuse_factorization
    factor_s, n_kry, factored = 0.0, 0, False
    while True:
        K, Kff, n_proj = _assemble_reduced(p, w, xk, project)
        rhs = _newton_rhs(p, K, state)
        du = None
        # forcing term ∝ the residual keeps Newton's quadratic convergence (and the final state as
        # accurate as an exact Newton step leaves it)
        rtol = max(1e-14, min(p.opts.krylov_rtol, state.res / max(1.0, state.f_ref)))
        if not direct and not project and p.cache.factorization is not None:
            du, n = _krylov(p, w, Kff, rhs, rtol, p.cache.factorization)
            n_kry += n
            direct = True  # if this direction is refused, factor the current tangent
        if du is None:
            fac, factor_s = _factor(p, w, Kff)
            if fac is None:
                if project:
                    raise StepFailed("projected stiffness still not positive definite")
                project = True
                continue
            factored = True
            du, n = _factored_solve(p, w, Kff, rhs, rtol, fac)
            n_kry += n
        refusal, slope = _refusal(du, state)
        if refusal is None:
            return _Direction(du, slope, n_proj, factor_s, factored, n_kry)
        if project:
            raise StepFailed(refusal)
        project = project or factored
        direct = True


def _krylov(p: NewtonProblem, w: NewtonWork, Kff: sp.csr_matrix, rhs: np.ndarray, rtol: float, fac: Factorization
            ) -> tuple[np.ndarray | None, int]:
    """CG on K_ff preconditioned by ``fac``: the solution (None if CG gave up) and the iterations spent."""
    t = time.perf_counter()
    kr = pcg(Kff, rhs, fac.solve, rtol, p.opts.krylov_max_iterations)
    w.timings["krylov"] += time.perf_counter() - t
    w.krylov_iterations += kr.iterations
    return kr.x, kr.iterations


def _factor(p: NewtonProblem, w: NewtonWork, Kff: sp.csr_matrix) -> tuple[Factorization | None, float]:
    """Factor K_ff into the cache: the factorization (None if not positive definite) and the seconds it took."""
    t = time.perf_counter()
    w.factorizations += 1
    try:
        fac = p.cache.solver.factor(Kff)
    except NotPositiveDefinite:
        p.cache.factorization = None  # the backend's state was reset
        w.timings["factor"] += time.perf_counter() - t
        return None, 0.0
    p.cache.factorization = fac
    factor_s = time.perf_counter() - t
    w.timings["factor"] += factor_s
    return fac, factor_s


def _factored_solve(p: NewtonProblem, w: NewtonWork, Kff: sp.csr_matrix, rhs: np.ndarray, rtol: float,
                    fac: Factorization) -> tuple[np.ndarray, int]:
    """Solve K_ff du = rhs with a fresh factorization (a single-precision one only preconditions CG)."""
    t = time.perf_counter()
    n_kry = 0
    if p.cache.solver.precision == "single":  # a preconditioner, not an exact solve
        kr = pcg(Kff, rhs, fac.solve, rtol, p.opts.krylov_max_iterations)
        n_kry = kr.iterations
        w.krylov_iterations += kr.iterations
        du = np.full(rhs.shape, np.nan) if kr.x is None else kr.x
    else:
        du = fac.solve(rhs)
    w.timings["solve"] += time.perf_counter() - t
    return du, n_kry


def _refusal(du: np.ndarray, state: _Iterate) -> tuple[str | None, float]:
    """Why a direction cannot be used (non-finite, or not a descent direction once the boundary is in), or None;
    and its slope r_f·du."""
    if not np.all(np.isfinite(du)):
        return "non-finite Newton direction", math.nan
    slope = float(state.rf @ du)
    if state.boundary_done and slope >= 0.0:
        return "no descent direction even with PSD projection", slope
    return None, slope


def _line_search(p: NewtonProblem, w: NewtonWork, xk: np.ndarray, state: _Iterate, direction: _Direction) -> _Step:
    """Backtracking on the free DoFs with the boundary put on this step's target.

    While the boundary moves in, any scale that keeps every J > 0 is taken, from at most ``_BOUNDARY_HALVINGS``
    halvings: a start with the boundary in place and the free nodes barely moved is nearly inverted (forces of
    1e9 N and more were seen) and Newton stalls from there, so a smaller load step is the better answer. Once the
    boundary is in, the Armijo condition on the potential decides.
    """
    d = np.zeros(3 * p.mesh.n_nodes)
    d[p.free_idx] = direction.du
    d = d.reshape(p.mesh.n_nodes, 3)
    base = xk.copy()
    base.reshape(-1)[p.cdofs] = state.target
    t = time.perf_counter()
    alpha = 1.0
    accepted = False
    for _ in range(30 if state.boundary_done else _BOUNDARY_HALVINGS + 1):
        xt = base + alpha * d
        e_t = total_energy(p.mesh, p.material, xt)
        if np.isfinite(e_t):
            if not state.boundary_done:
                accepted = True
                break
            e_t -= float(np.sum(state.fext * xt))
            if _armijo_accepts(p, state, direction, xt, e_t, alpha):
                accepted = True
                break
        alpha *= 0.5
    w.timings["line_search"] += time.perf_counter() - t
    return _Step(accepted, alpha, xt, e_t)


def _armijo_accepts(p: NewtonProblem, state: _Iterate, direction: _Direction, xt: np.ndarray, e_t: float,
                    alpha: float) -> bool:
    """Armijo decrease of the potential ``e_t`` at ``xt``; near convergence, where energy differences drown in
    round-off, a full step that reduces the residual."""
    if e_t <= state.energy + p.opts.armijo * alpha * direction.slope:
        return True
    if alpha == 1.0 and abs(e_t - state.energy) <= 1e-12 * max(1.0, abs(state.energy)):
        r_t = (internal_forces(p.mesh, p.material, xt) - state.fext).ravel()[p.free_idx]
        return bool(np.linalg.norm(r_t) < state.res)
    return False


def _log_converged(p: NewtonProblem, w: NewtonWork, state: _Iterate, step: int, it: int) -> None:
    """Record the converged iterate of a load step."""
    w.log.append({"step": step, "iteration": it, "energy": state.energy, "residual": state.res, "alpha": 0.0,
                  "projected": 0, "factor_s": 0.0, "tolerance": state.tolerance(p.opts), "factorized": False,
                  "krylov": 0})
    if p.opts.verbose:
        print(f"  step {step} it {it}: converged |r|={state.res:.3e} (ref {state.f_ref:.3e})")


def _log_iteration(p: NewtonProblem, w: NewtonWork, state: _Iterate, direction: _Direction, trial: _Step, step: int,
                   it: int) -> None:
    """Record one Newton iteration."""
    w.log.append({"step": step, "iteration": it, "energy": state.energy, "residual": state.res,
                  "alpha": trial.alpha if trial.accepted else 0.0, "projected": int(direction.projected),
                  "factor_s": direction.factor_s, "tolerance": state.tolerance(p.opts),
                  "factorized": direction.factored, "krylov": direction.krylov})
    if p.opts.verbose:
        print(f"  step {step} it {it}: |r|={state.res:.3e} (ref {state.f_ref:.3e}) E={state.energy:.6e} "
              f"alpha={trial.alpha:.3g} projected={direction.projected} factor={direction.factor_s:.3f}s "
              f"cg={direction.krylov}")
