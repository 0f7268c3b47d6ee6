"""Multi-pose skin thickness optimization: sample heights h such that the skin, posed by its attachments, matches
target surfaces.

Objective (dimensionless): E(h) = Σ_k Σ_i∈R ½ w_i ‖x_k,i(h) − q_k,i‖² / (Σ_i w_i ℓ²) (matching over the region R
with per-node weights w, 1 unless given, per pose k)
+ a log barrier keeping h inside [h_min, h_max] + a quadratic penalty once h comes within ``margin`` of a bound
+ a warp regularization W(X(h); X_ref) / (μ V): the elastic energy of the warped rest shape measured against the
reference one, which grows without bound as a warped element flattens (keeps the warp well-conditioned).

Two formulations. **Adjoint** (:func:`optimize_adjoint`): every evaluation solves each pose to exact equilibrium;
the gradient comes from one adjoint solve per pose with the factorization of K_ff reused, dE/dh = −Σ λ_kᵀ ∂f/∂X D;
steps are Gauss-Newton (forward sensitivities dx/dh = −K_ff⁻¹ ∂f/∂X D, S solves on the same factorization) or
L-BFGS, each with a backtracking line search. **Joint** (:func:`optimize_joint`): Gauss-Newton over all pose states
and h together on the equilibrium residuals and the matching residuals, a sparse factorization per iteration
with an identity shift when it fails.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from offline.fem import energy as _en
from offline.fem.linsolve import make_solver
from offline.fem.materials import Material
from offline.fem.rest_shape import mixed_stiffness
from offline.fem.solve import Dirichlet, NotConverged, SolverOptions, solve_static

from .warp import ThicknessWarp


@dataclass(frozen=True, eq=False)
class Pose:
    """One target: Dirichlet conditions on attachment nodes (which the warp keeps fixed) and the target positions
    (R, 3) of the problem's region nodes."""

    dirichlet: Dirichlet
    target: np.ndarray


@dataclass(frozen=True, eq=False)
class ThicknessProblem:
    """A thickness design problem: warp, material, poses, matching region (node indices), bounds and weights."""

    warp: ThicknessWarp
    material: Material
    poses: tuple[Pose, ...]
    region: np.ndarray
    h_min: float
    h_max: float
    barrier_weight: float = 1e-10
    penalty_weight: float = 1e-3
    margin: float = 0.05
    warp_weight: float = 1e-9
    length_scale: float = 1e-3
    region_weights: np.ndarray | None = None  # (R,) per region node, >= 0; None: all 1
    solver: SolverOptions = field(default_factory=lambda: SolverOptions(tol_force=1e-11, load_steps="auto"))

    def __post_init__(self) -> None:
        if not (0 < self.h_min < self.h_max):
            raise ValueError(f"need 0 < h_min < h_max, got h_min={self.h_min}, h_max={self.h_max}")
        if not self.poses:
            raise ValueError("a thickness problem needs at least one pose")
        region = np.asarray(self.region, dtype=np.int64)
        for k, p in enumerate(self.poses):
            if np.asarray(p.target).shape != (region.size, 3):
                raise ValueError(f"pose {k}: target must have shape ({region.size}, 3), got {np.shape(p.target)}")
            moved = p.dirichlet.nodes[~self.warp.locked[p.dirichlet.nodes]]
            if moved.size:
                raise ValueError(f"pose {k}: Dirichlet node {moved[0]} is not locked by the warp; constrained "
                                 "nodes must be attachment nodes whose rest geometry the warp keeps")
        object.__setattr__(self, "region", region)
        if self.region_weights is not None:
            w = np.asarray(self.region_weights, dtype=np.float64).reshape(-1)
            if w.shape != (region.size,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
                raise ValueError(f"region_weights must be {region.size} finite values >= 0, not all 0 "
                                 f"(got shape {w.shape})")
            object.__setattr__(self, "region_weights", w)

    @property
    def node_weights(self) -> np.ndarray:
        """Matching weight of every region node (R,): ``region_weights`` or all 1."""
        return np.ones(self.region.size) if self.region_weights is None else self.region_weights

    def check_heights(self, h: np.ndarray) -> np.ndarray:
        """``h`` as a float array, refused when outside the open interval (h_min, h_max)."""
        h = self.warp._check(h)
        if np.any(h <= self.h_min) or np.any(h >= self.h_max):
            raise ValueError(f"sample heights must lie strictly inside ({self.h_min}, {self.h_max}) m, got "
                             f"[{h.min()}, {h.max()}]")
        return h


# ------------------------------------------------------------------------------------------------ evaluation
@dataclass
class State:
    """Equilibrium of every pose at heights h, with what the derivatives need."""

    h: np.ndarray
    xs: list[np.ndarray]
    value: float
    match: float
    reg: float
    solves: int


def solve_poses(problem: ThicknessProblem, h: np.ndarray, warm: Sequence[np.ndarray] | None = None) -> State | None:
    """Solve every pose at heights h (warm-started when possible); None if the rest shape or a solve fails."""
    X = problem.warp.rest_positions(h)
    if _en.min_jacobian(problem.warp.mesh, X) <= 0:  # warped rest mesh inverted
        return None
    mesh = problem.warp.rest_mesh(h)
    xs = []
    for k, pose in enumerate(problem.poses):
        x0 = None
        if warm is not None and _en.min_jacobian(mesh, warm[k]) > 0:
            x0 = warm[k]
        try:
            res = solve_static(mesh, problem.material, pose.dirichlet, x0=x0, options=problem.solver)
        except NotConverged:
            return None
        xs.append(res.x)
    match = _match_value(problem, xs)
    reg = _reg_value(problem, h)
    return State(h, xs, match + reg, match, reg, len(xs))


def _match_scale(problem: ThicknessProblem) -> float:
    return 1.0 / (float(problem.node_weights.sum()) * problem.length_scale ** 2)


def _dof_weights(problem: ThicknessProblem) -> np.ndarray:
    """s w_i repeated per coordinate (3R,): the matching term is ½ Σ (s w) (x − q)² over region DoFs."""
    return np.repeat(_match_scale(problem) * problem.node_weights, 3)


def _match_value(problem: ThicknessProblem, xs: Sequence[np.ndarray]) -> float:
    w = _dof_weights(problem)
    pairs = zip(xs, problem.poses, strict=True)
    return float(sum(0.5 * np.sum(w * (x[problem.region] - p.target).ravel() ** 2) for x, p in pairs))


def _warp_norm(problem: ThicknessProblem) -> float:
    vol = float(np.sum(_en._mesh_data(problem.warp.mesh).wdet))
    return 1.0 / (problem.material.shear_modulus * vol)


def _reg_terms(problem: ThicknessProblem, h: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Bounds terms: value, gradient and (diagonal) Hessian in h."""
    rng = problem.h_max - problem.h_min
    lo, hi = (h - problem.h_min) / rng, (problem.h_max - h) / rng
    if np.any(lo <= 0) or np.any(hi <= 0):
        return np.inf, np.zeros_like(h), np.zeros_like(h)
    mu = problem.barrier_weight
    val = -mu * np.sum(np.log(lo) + np.log(hi))
    g = -mu * (1.0 / lo - 1.0 / hi) / rng
    H = mu * (1.0 / lo ** 2 + 1.0 / hi ** 2) / rng ** 2
    m = problem.margin
    under, over = np.maximum(0.0, m - lo), np.maximum(0.0, m - hi)
    gq = problem.penalty_weight
    val += gq * np.sum(under ** 2 + over ** 2)
    g += 2.0 * gq * (-under + over) / rng
    H += 2.0 * gq * ((under > 0) + (over > 0)) / rng ** 2
    return float(val), g, H


def _reg_value(problem: ThicknessProblem, h: np.ndarray) -> float:
    val = _reg_terms(problem, h)[0]
    if problem.warp_weight > 0:
        X = problem.warp.rest_positions(h)
        val += problem.warp_weight * _warp_norm(problem) * _en.total_energy(problem.warp.mesh, problem.material, X)
    return val


def _reg_derivatives(problem: ThicknessProblem, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (S,) and Gauss-Newton-style Hessian (S, S) of the regularization."""
    _, g, Hd = _reg_terms(problem, h)
    H = np.diag(Hd)
    if problem.warp_weight > 0:
        X = problem.warp.rest_positions(h)
        c = problem.warp_weight * _warp_norm(problem)
        D = problem.warp.D
        g = g + c * (D.T @ _en.internal_forces(problem.warp.mesh, problem.material, X).ravel())
        K = _en.stiffness(problem.warp.mesh, problem.material, X, project_psd=True)
        H = H + c * (D.T @ (K @ D)).toarray()
    return g, H


def _region_dofs(problem: ThicknessProblem) -> np.ndarray:
    return (3 * problem.region[:, None] + np.arange(3)).ravel()


def _linearization(problem: ThicknessProblem, state: State, k: int):
    """Factorization of K_ff, free DoFs and ∂f_f/∂h (free × S) for pose k at the state's equilibrium."""
    mesh = problem.warp.rest_mesh(state.h)
    x = state.xs[k]
    K = _en.stiffness(mesh, problem.material, x)
    free = np.ones(K.shape[0], dtype=bool)
    free[problem.poses[k].dirichlet.dofs] = False
    free_idx = np.flatnonzero(free)
    Kff = K[free_idx][:, free_idx].tocsr()
    fac = make_solver(problem.solver.backend).factor(Kff)
    B = mixed_stiffness(mesh, problem.material, x)
    dfdh = (B[free_idx] @ problem.warp.D)
    return fac, free_idx, dfdh, Kff


def adjoint_gradient(problem: ThicknessProblem, state: State) -> np.ndarray:
    """dE/dh by one adjoint solve per pose: K_ff λ = ∂E/∂x_f, dE/dh = −λᵀ ∂f_f/∂h (+ the regularization's)."""
    w = _dof_weights(problem)
    g = _reg_derivatives(problem, state.h)[0].copy()
    rd = _region_dofs(problem)
    for k, pose in enumerate(problem.poses):
        fac, free_idx, dfdh, _ = _linearization(problem, state, k)
        dEdx = np.zeros(3 * problem.warp.mesh.n_nodes)
        dEdx[rd] = w * (state.xs[k][problem.region] - pose.target).ravel()
        lam = fac.solve(dEdx[free_idx])
        g -= np.asarray(dfdh.T @ lam).ravel()
    return g


def sensitivities(problem: ThicknessProblem, state: State) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per pose, the matching residual r_k (3R,) and its Jacobian dr_k/dh (3R, S), both scaled so E_match = ½Σ‖r‖²."""
    sq = np.sqrt(_dof_weights(problem))
    rs, Js = [], []
    N3 = 3 * problem.warp.mesh.n_nodes
    rd = _region_dofs(problem)
    for k, pose in enumerate(problem.poses):
        fac, free_idx, dfdh, _ = _linearization(problem, state, k)
        dxf = -fac.solve(np.asarray(dfdh.toarray() if sp.issparse(dfdh) else dfdh))  # (free, S)
        dx = np.zeros((N3, dxf.shape[1]))
        dx[free_idx] = dxf
        rs.append(sq * (state.xs[k][problem.region] - pose.target).ravel())
        Js.append(sq[:, None] * dx[rd])
    return rs, Js


def reachability_split(rs: Sequence[np.ndarray], Js: Sequence[np.ndarray], lower: np.ndarray | None = None,
                       upper: np.ndarray | None = None, rcond: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Split each pose's matching term ½‖r_k‖² into what thickness can change and what it cannot, to first order.

    The best joint height change for the linearized residuals r_k + J_k dh (least squares over every pose, within
    ``lower`` <= dh <= ``upper`` when given: the bounds' room; unbounded otherwise) leaves ½‖r_k + J_k dh*‖² per
    pose: the reachability residual, the share no thickness field can remove near the current design. Returns
    (residual per pose, the best change dh*); match_k − residual_k is what thickness can still gain for pose k
    (negative for a pose that the joint optimum sacrifices).
    """
    r = np.concatenate(rs)
    J = np.vstack(Js)
    if lower is None and upper is None:
        dh = np.linalg.lstsq(J, -r, rcond=rcond)[0]
    else:
        from scipy.optimize import lsq_linear

        S = J.shape[1]
        lo = np.full(S, -np.inf) if lower is None else np.minimum(np.asarray(lower, dtype=np.float64), 0.0)
        hi = np.full(S, np.inf) if upper is None else np.maximum(np.asarray(upper, dtype=np.float64), 0.0)
        dh = lsq_linear(J, -r, bounds=(lo, hi), method="bvls", tol=1e-12).x
    return np.array([0.5 * float(np.sum((rk + Jk @ dh) ** 2)) for rk, Jk in zip(rs, Js, strict=True)]), dh


# ------------------------------------------------------------------------------------------------ optimizers
@dataclass
class OptimizeResult:
    """Heights found, the log (one dict per iteration), counts of pose solves and linear solves, wall time."""

    h: np.ndarray
    xs: list[np.ndarray]
    value: float
    iterations: int
    converged: bool
    log: list[dict]
    forward_solves: int
    seconds: float
    method: str


def _line_search(problem, state: State, step: np.ndarray, slope: float, counts: dict):
    alpha = 1.0
    # stay strictly inside the bounds (fraction-to-boundary rule)
    h = state.h
    with np.errstate(divide="ignore", invalid="ignore"):
        lim_lo = np.where(step < 0, (problem.h_min - h) / step, np.inf)
        lim_hi = np.where(step > 0, (problem.h_max - h) / step, np.inf)
    amax = float(min(lim_lo.min(), lim_hi.min()))
    if amax <= 1.0:
        alpha = 0.95 * amax
    for _ in range(30):
        trial = solve_poses(problem, h + alpha * step, state.xs)
        counts["forward"] += len(problem.poses)
        if trial is not None and trial.value <= state.value + 1e-4 * alpha * slope:
            return trial, alpha
        alpha *= 0.5
    return None, 0.0


def _progress(method: str, it: int, state: State, step_norm: float, t0: float, verbose: bool) -> dict:
    entry = {"iteration": it, "objective": state.value, "match": state.match, "reg": state.reg,
             "step_max_m": step_norm, "seconds": time.perf_counter() - t0}
    if verbose:
        print(f"[{method}] it {it:3d}  E={state.value:.6e}  match={state.match:.3e}  reg={state.reg:.3e}  "
              f"|dh|max={step_norm * 1e3:.4f} mm  t={entry['seconds']:.1f}s", flush=True)
    return entry


def optimize_adjoint(problem: ThicknessProblem, h0: np.ndarray, *, method: str = "gauss-newton",
                     max_iterations: int = 50, tol_step: float = 1e-9, tol_value: float = 1e-16,
                     tol_gain: float = 0.0, trust_radius: float = 0.25, barrier_decay: float = 0.1,
                     verbose: bool = False,
                     warm: Sequence[np.ndarray] | None = None) -> OptimizeResult:
    """Minimise E(h) with exact equilibrium per pose; ``method`` is ``gauss-newton`` or ``lbfgs``.

    ``warm``: one state (N, 3) per pose to start the first equilibrium solves from (e.g. the previous design's).

    Stops when the largest height step is below ``tol_step`` (m), E below ``tol_value``, or (Gauss-Newton) when
    the model predicts that the next step gains less than ``tol_gain`` × the matching term. Gauss-Newton steps
    minimise the model over the bounds and a trust region (``trust_radius`` × the bound range at first, halved
    after a poor step, doubled after a good one that reached it; :func:`_box_step`): the part of the
    objective thickness can still change is then spent (each log entry has ``predicted_gain``, the model's
    decrease for the step taken, relative to the matching term; each state linearized also has
    ``match_per_pose`` and ``reachability_residual_per_pose``, see :func:`reachability_split`). The barrier weight is
    multiplied by ``barrier_decay`` after each iteration (interior-point continuation), so the bounds do not bias
    an interior optimum.
    """
    if method not in ("gauss-newton", "lbfgs"):
        raise ValueError(f"unknown method {method!r}; use 'gauss-newton' or 'lbfgs'")
    t0 = time.perf_counter()
    h = problem.check_heights(h0).copy()
    counts = {"forward": 0}
    state = solve_poses(problem, h, warm)
    if state is None and warm is not None:
        state = solve_poses(problem, h, None)
    counts["forward"] += len(problem.poses)
    if state is None:
        raise ValueError("the starting heights give an inverted rest shape or a pose that does not converge")
    log = [_progress(method, 0, state, 0.0, t0, verbose)]
    radius = trust_radius * (problem.h_max - problem.h_min)
    mem_s: list[np.ndarray] = []
    mem_y: list[np.ndarray] = []
    g_prev = None
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        if method == "gauss-newton":
            rs, Js = sensitivities(problem, state)
            g_reg, H_reg = _reg_derivatives(problem, state.h)
            g = g_reg + sum(J.T @ r for J, r in zip(Js, rs, strict=True))
            H = H_reg + sum(J.T @ J for J in Js)
            step = _box_step(problem, state.h, g, H, radius)
            resid, _ = reachability_split(rs, Js, problem.h_min - state.h, problem.h_max - state.h)
            log[-1]["match_per_pose"] = [0.5 * float(r @ r) for r in rs]
            log[-1]["reachability_residual_per_pose"] = resid.tolist()
            predicted = -float(g @ step + 0.5 * step @ H @ step) / max(state.match, 1e-300)
            if tol_gain > 0 and predicted < tol_gain:
                log[-1]["next_predicted_gain"] = predicted
                converged = True
                break
        else:
            g = adjoint_gradient(problem, state)
            if g_prev is not None and mem_s:
                y = g - g_prev
                if float(y @ mem_s[-1]) > 1e-300:
                    mem_y.append(y)
                else:
                    mem_s.pop()
            step = _lbfgs_direction(g, mem_s[-10:], mem_y[-10:])
            if not mem_s:  # first step: at most 2 % of the bound range
                step *= 0.02 * (problem.h_max - problem.h_min) / max(np.abs(step).max(), 1e-300)
        slope = float(g @ step)
        if slope >= 0:
            step, slope = -g, -float(g @ g)
        new, alpha = _line_search(problem, state, step, slope, counts)
        if new is None:
            break
        if method == "lbfgs":
            mem_s.append(alpha * step)
            g_prev = g
        dh = float(np.abs(new.h - state.h).max())
        state = new
        log.append(_progress(method, it, state, dh, t0, verbose))
        if method == "gauss-newton":
            log[-1]["predicted_gain"] = predicted
            actual = (log[-2]["objective"] - state.value) / max(log[-2]["match"], 1e-300)
            if alpha < 1.0 or actual < 0.25 * predicted:
                radius *= 0.5
            elif actual > 0.75 * predicted and np.abs(alpha * step).max() > 0.9 * radius:
                radius = min(2.0 * radius, problem.h_max - problem.h_min)
        problem = replace(problem, barrier_weight=problem.barrier_weight * barrier_decay)
        state.reg = _reg_value(problem, state.h)
        state.value = state.match + state.reg
        if dh < tol_step or state.value < tol_value:
            converged = True
            break
    return OptimizeResult(state.h, state.xs, state.value, it, converged, log, counts["forward"],
                          time.perf_counter() - t0, f"adjoint-{method}")


def _box_step(problem: ThicknessProblem, h: np.ndarray, g: np.ndarray, H: np.ndarray, radius: float,
              band: float = 0.01) -> np.ndarray:
    """The Gauss-Newton model's minimiser g·d + ½ dᵀ H d over the box: heights kept ``band`` (of the bound range)
    inside their bounds and each changed by at most ``radius`` (a trust region). On the face the unconstrained
    step is ill-conditioned (sample combinations with little effect get metre-sized changes), so the
    fraction-to-boundary rule cut it to nothing; the box step stays meaningful."""
    from scipy.optimize import lsq_linear

    rng = problem.h_max - problem.h_min
    lo = np.minimum(np.maximum(problem.h_min + band * rng - h, -radius), 0.0)
    hi = np.maximum(np.minimum(problem.h_max - band * rng - h, radius), 0.0)
    L = np.linalg.cholesky(H + 1e-12 * np.trace(H) / len(h) * np.eye(len(h)))
    b = -np.linalg.solve(L, g)  # ½‖Lᵀ d − b‖² = g·d + ½ dᵀ H d + const
    return lsq_linear(L.T, b, bounds=(lo, hi), method="bvls", tol=1e-12).x


def _solve_general(A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Solve a general (unsymmetric, indefinite) sparse system: PARDISO when installed, else SuperLU."""
    try:
        import pypardiso
    except ImportError:
        return spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A").solve(b)
    return pypardiso.spsolve(sp.csr_matrix(A), b)


def _lbfgs_direction(g: np.ndarray, S: list[np.ndarray], Y: list[np.ndarray]) -> np.ndarray:
    q = -g.copy()
    alphas = []
    for s, y in zip(reversed(S), reversed(Y), strict=True):
        a = float(s @ q) / float(y @ s)
        alphas.append(a)
        q -= a * y
    if S:
        q *= float(S[-1] @ Y[-1]) / float(Y[-1] @ Y[-1])
    for (s, y), a in zip(zip(S, Y, strict=True), reversed(alphas), strict=True):
        b = float(y @ q) / float(y @ s)
        q += (a - b) * s
    return q


def optimize_joint(problem: ThicknessProblem, h0: np.ndarray, *, max_iterations: int = 50,
                   tol_step: float = 1e-9, equilibrium_weight: float = 1.0, barrier_decay: float = 0.1,
                   verbose: bool = False) -> OptimizeResult:
    """Gauss-Newton on all pose states and h at once (the joint formulation).

    Residuals: the free internal forces of every pose (weighted by ``equilibrium_weight`` after scaling by a
    typical force μℓ²) and the matching residuals; the normal equations are one sparse system per iteration
    in augmented form [I −J; Jᵀ H_reg], factorized with PARDISO or SuperLU (on failure a growing identity shift
    is added to the unknowns' block), followed by a backtracking line search on the merit ½‖r‖² +
    regularization. Starts from a forward simulation at h0.
    """
    t0 = time.perf_counter()
    h = problem.check_heights(h0).copy()
    first = solve_poses(problem, h, None)
    if first is None:
        raise ValueError("the starting heights give an inverted rest shape or a pose that does not converge")
    counts = {"forward": len(problem.poses)}
    xs = [x.copy() for x in first.xs]
    N3 = 3 * problem.warp.mesh.n_nodes
    frees = []
    for pose in problem.poses:
        free = np.ones(N3, dtype=bool)
        free[pose.dirichlet.dofs] = False
        frees.append(np.flatnonzero(free))
    f_scale = equilibrium_weight / (problem.material.shear_modulus * problem.length_scale ** 2)
    sq = np.sqrt(_dof_weights(problem))
    rd = _region_dofs(problem)
    S = len(h)

    def residuals(h_, xs_):
        X = problem.warp.rest_positions(h_)
        if _en.min_jacobian(problem.warp.mesh, X) <= 0:
            return None
        mesh = problem.warp.rest_mesh(h_)
        out = []
        for k, pose in enumerate(problem.poses):
            if _en.min_jacobian(mesh, xs_[k]) <= 0:
                return None
            f = _en.internal_forces(mesh, problem.material, xs_[k]).ravel()[frees[k]]
            out.append((f_scale * f, sq * (xs_[k][problem.region] - pose.target).ravel()))
        return out

    def merit(h_, xs_):
        rr = residuals(h_, xs_)
        if rr is None:
            return np.inf, None
        val = sum(0.5 * (fe @ fe + rm @ rm) for fe, rm in rr) + _reg_value(problem, h_)
        return float(val), rr

    value, rr = merit(h, xs)
    state = State(h, xs, value, _match_value(problem, xs), _reg_value(problem, h), 0)
    log = [_progress("joint", 0, state, 0.0, t0, verbose)]
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        mesh = problem.warp.rest_mesh(h)
        rhs = []
        nf = [f.size for f in frees]
        offs = np.concatenate([[0], np.cumsum(nf)])
        n_unk = offs[-1] + S
        rows = []  # per pose [equilibrium; matching], columns [u_1 ... u_m, h]
        for k in range(len(problem.poses)):
            K = _en.stiffness(mesh, problem.material, xs[k])
            B = mixed_stiffness(mesh, problem.material, xs[k])
            Kff = K[frees[k]][:, frees[k]]
            dfdh = B[frees[k]] @ problem.warp.D
            Je = sp.hstack([sp.csr_matrix((nf[k], offs[k])), f_scale * Kff,
                            sp.csr_matrix((nf[k], offs[-1] - offs[k + 1])), f_scale * dfdh])
            sel = np.searchsorted(frees[k], rd)
            ok = frees[k][np.minimum(sel, nf[k] - 1)] == rd
            P = sp.csr_matrix((sq[ok], (np.flatnonzero(ok), sel[ok])), shape=(rd.size, nf[k]))
            Jm = sp.hstack([sp.csr_matrix((rd.size, offs[k])), P, sp.csr_matrix((rd.size, n_unk - offs[k + 1]))])
            rows += [Je, Jm]
            rhs += [rr[k][0], rr[k][1]]
        J = sp.vstack(rows).tocsr()
        r = np.concatenate(rhs)
        g_reg, H_reg = _reg_derivatives(problem, h)
        g = J.T @ r
        g[offs[-1]:] += g_reg
        # Augmented form of the Gauss-Newton normal equations (condition ~ κ(J), not κ(J)²):
        # [I  −J; Jᵀ  H_reg] [y; s] = [r; −g_reg] with y = r + J s.
        n_r = r.size
        Hr = sp.bmat([[sp.csr_matrix((offs[-1], offs[-1])), None], [None, sp.csr_matrix(H_reg)]]).tocsr()
        shift = 0.0
        step = None
        for _ in range(8):
            try:
                Hs = Hr if shift == 0 else Hr + shift * sp.identity(n_unk, format="csr")
                A = sp.bmat([[sp.identity(n_r, format="csr"), -J], [J.T, Hs]]).tocsc()
                sol = _solve_general(A, np.concatenate([r, -np.r_[np.zeros(offs[-1]), g_reg]]))
                step = sol[n_r:]
                if np.all(np.isfinite(step)):
                    break
            except Exception:  # singular or failed factorization: shift and retry
                pass
            shift = max(1e-12, 10 * shift)
            step = None
        if step is None:
            break
        slope = float(g @ step)
        dh_full = step[offs[-1]:]
        alpha = 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            lims = np.concatenate([np.where(dh_full < 0, (problem.h_min - h) / dh_full, np.inf),
                                   np.where(dh_full > 0, (problem.h_max - h) / dh_full, np.inf)])
        if lims.min() <= 1.0:
            alpha = 0.95 * float(lims.min())
        accepted = False
        for _ in range(30):
            h_t = h + alpha * dh_full
            xs_t = []
            for k in range(len(problem.poses)):
                xk = xs[k].copy().ravel()
                xk[frees[k]] += alpha * step[offs[k]:offs[k + 1]]
                xs_t.append(xk.reshape(-1, 3))
            v_t, rr_t = merit(h_t, xs_t)
            if v_t <= value + 1e-4 * alpha * slope:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            break
        dh = float(np.abs(h_t - h).max())
        h, xs, value, rr = h_t, xs_t, v_t, rr_t
        problem = replace(problem, barrier_weight=problem.barrier_weight * barrier_decay)
        state = State(h, xs, value, _match_value(problem, xs), _reg_value(problem, h), 0)
        log.append(_progress("joint", it, state, dh, t0, verbose))
        if dh < tol_step and np.abs(step).max() < tol_step:
            converged = True
            break
    # report the states at exact equilibrium for the heights found
    final = solve_poses(problem, h, xs)
    counts["forward"] += len(problem.poses)
    xs_eq = final.xs if final is not None else xs
    return OptimizeResult(h, xs_eq, value, it, converged, log, counts["forward"], time.perf_counter() - t0,
                          "joint-gauss-newton")
