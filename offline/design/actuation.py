"""Actuation optimization: per target expression, the actuator values whose FEM-simulated skin best matches it.

The FEM-exact counterpart of the runtime's predictor-based inverse (``models.ksnn_solve``). For actuator values p
the attachment nodes sit at c(p) (the link map moves each link's node set rigidly); the free nodes settle at the
quasi-static equilibrium x(p). The objective over a matching region R (dimensionless, ℓ a length scale):

    E(p) = ½ ‖x_R(p) − q‖² / (n_R ℓ²)  +  w_lim Σ_i [max(0, m − u_i)² + max(0, u_i − 1 + m)²]
                                        +  w_spread Σ_coupled max(0, |p_a − p_b| − s)² / range²

with u_i = (p_i − lo_i) / (hi_i − lo_i): the limits act as a regularization that grows within a margin m of each
bound, and every trial point is also projected into the box and the coupled groups' spread (so no pose outside
the head's limits is ever simulated). "together"/"mirror" groups are a change of variables p = B z.

Steps are Gauss-Newton (Levenberg-Marquardt damped) with the FEM sensitivities of the direct method: at the
equilibrium, dx_f/dp = −K_ff⁻¹ K_fc dc/dp, one factorization of K_ff per iteration serving all actuator columns
(the solver object keeps the symbolic analysis across iterations, targets and adjoint solves). The adjoint form of
the same gradient (one solve, K_ff λ = ∂E/∂x_f) is :func:`adjoint_gradient`, used to check the direct one. Targets
are warm-started: each starts from the best of the previous target's solution and any caller-given start (the
predictor's inverse), and its Newton solves start from the previous equilibrium.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from offline.fem import energy as _en
from offline.fem.linsolve import make_solver
from offline.fem.materials import Material
from offline.fem.mesh import TetMesh
from offline.fem.solve import Dirichlet, NotConverged, SolverOptions, solve_static

from .strain_constraint import StrainConstraint

Boundary = Callable[[np.ndarray], Dirichlet]


# ------------------------------------------------------------------------------------------------ actuation space
@dataclass(frozen=True, eq=False)
class ActuationSpace:
    """Actuators (SI values), their limits and group constraints, and the attachment motion c(p).

    ``boundary(p)`` returns the Dirichlet conditions of pose p; its node order must not depend on p.
    ``together``: groups moving as one, each ``(indices, gains)`` with p_i = gain_i · z (gains ±1 for mirrors).
    ``coupled``: groups ``(indices, max_spread)`` whose values may differ by at most ``max_spread``.
    """

    names: tuple[str, ...]
    lo: np.ndarray
    hi: np.ndarray
    neutral: np.ndarray
    boundary: Boundary
    together: tuple[tuple[tuple[int, ...], tuple[float, ...]], ...] = ()
    coupled: tuple[tuple[tuple[int, ...], float], ...] = ()
    fd_step: float = 1e-6  # central-difference step of dc/dp, as a fraction of each actuator's range

    def __post_init__(self) -> None:
        A = len(self.names)
        lo = np.asarray(self.lo, dtype=np.float64).reshape(-1)
        hi = np.asarray(self.hi, dtype=np.float64).reshape(-1)
        neutral = np.asarray(self.neutral, dtype=np.float64).reshape(-1)
        for name, v in (("lo", lo), ("hi", hi), ("neutral", neutral)):
            if v.shape != (A,) or not np.all(np.isfinite(v)):
                raise ValueError(f"ActuationSpace.{name} must be {A} finite values, got shape {v.shape}")
        if np.any(hi <= lo):
            bad = int(np.argmax(hi <= lo))
            raise ValueError(f"actuator {self.names[bad]!r}: max {hi[bad]} must exceed min {lo[bad]}")
        if np.any(neutral < lo) or np.any(neutral > hi):
            bad = int(np.argmax((neutral < lo) | (neutral > hi)))
            raise ValueError(f"actuator {self.names[bad]!r}: neutral {neutral[bad]} outside [{lo[bad]}, {hi[bad]}]")
        seen: set[int] = set()
        cols = []
        for idx, gains in self.together:
            if len(idx) != len(gains) or len(idx) < 2:
                raise ValueError(f"together group {idx}: needs >= 2 actuators and one gain each, got {gains}")
            if seen & set(idx):
                raise ValueError(f"actuator {self.names[sorted(seen & set(idx))[0]]!r} is in two together groups")
            if any(g == 0 for g in gains):
                raise ValueError(f"together group {idx}: gains must be non-zero, got {gains}")
            seen |= set(idx)
            col = np.zeros(A)
            col[list(idx)] = gains
            cols.append(col)
        for i in range(A):
            if i not in seen:
                col = np.zeros(A)
                col[i] = 1.0
                cols.append(col)
        order = np.argsort([int(np.flatnonzero(c)[0]) for c in cols], kind="stable")
        B = np.stack([cols[k] for k in order], axis=1)  # (A, Z)
        for idx, spread in self.coupled:
            if len(idx) < 2 or not spread > 0:
                raise ValueError(f"coupled group {idx}: needs >= 2 actuators and max_spread > 0, got {spread}")
        # Box of z: each p_i depends on one z_j with gain g: z_j within lo_i/g .. hi_i/g (swapped for g < 0).
        zlo = np.full(B.shape[1], -np.inf)
        zhi = np.full(B.shape[1], np.inf)
        for i in range(A):
            j = int(np.flatnonzero(B[i])[0])
            g = B[i, j]
            a, b = sorted((lo[i] / g, hi[i] / g))
            zlo[j], zhi[j] = max(zlo[j], a), min(zhi[j], b)
        if np.any(zlo > zhi):
            raise ValueError("a together group's limits do not overlap: no value satisfies all its actuators")
        for name, v in (("lo", lo), ("hi", hi), ("neutral", neutral)):
            object.__setattr__(self, name, v)
        object.__setattr__(self, "basis", B)
        object.__setattr__(self, "zlo", zlo)
        object.__setattr__(self, "zhi", zhi)

    @property
    def n_actuators(self) -> int:
        return len(self.names)

    @property
    def n_free(self) -> int:
        """Number of independent variables z (actuators less the together groups' ties)."""
        return int(self.basis.shape[1])

    def expand(self, z: np.ndarray) -> np.ndarray:
        """Actuator values p = B z."""
        return self.basis @ np.asarray(z, dtype=np.float64)

    def reduce(self, p: np.ndarray) -> np.ndarray:
        """Least-squares z for actuator values p (exact when p satisfies the together groups)."""
        return np.linalg.lstsq(self.basis, np.asarray(p, dtype=np.float64), rcond=None)[0]

    def project(self, z: np.ndarray) -> np.ndarray:
        """z moved into the limits and the coupled groups' spread (a few alternating passes)."""
        z = np.clip(np.asarray(z, dtype=np.float64), self.zlo, self.zhi)
        if not self.coupled:
            return z
        for _ in range(20):
            p = self.expand(z)
            moved = False
            for idx, spread in self.coupled:
                v = p[list(idx)]
                if v.max() - v.min() > spread * (1 + 1e-12):
                    mid = 0.5 * (v.max() + v.min())
                    p[list(idx)] = np.clip(v, mid - spread / 2, mid + spread / 2)
                    moved = True
            z = np.clip(self.reduce(p), self.zlo, self.zhi)
            if not moved:
                break
        return z

    def feasible(self, p: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether p lies inside the limits, the together ties and the coupled spreads."""
        p = np.asarray(p, dtype=np.float64)
        rng = self.hi - self.lo
        if np.any(p < self.lo - tol * rng) or np.any(p > self.hi + tol * rng):
            return False
        if np.abs(self.expand(self.reduce(p)) - p).max() > tol * rng.max():
            return False
        return all(np.ptp(p[list(idx)]) <= s * (1 + 1e-9) + tol for idx, s in self.coupled)

    def boundary_jacobian(self, p: np.ndarray) -> tuple[Dirichlet, np.ndarray]:
        """Dirichlet conditions at p and d(prescribed coordinates)/dp (C, A) by central differences."""
        p = np.asarray(p, dtype=np.float64)
        bc = self.boundary(p)
        J = np.zeros((bc.dof_values.size, self.n_actuators))
        for i in range(self.n_actuators):
            h = self.fd_step * (self.hi[i] - self.lo[i])
            e = np.zeros_like(p)
            e[i] = h
            J[:, i] = (self.boundary(p + e).dof_values - self.boundary(p - e).dof_values) / (2 * h)
        return bc, J

    @classmethod
    def from_head(cls, head, boundary: Boundary) -> ActuationSpace:
        """The space of a :class:`models.headspec.HeadSpec`: its limits, neutral, together/mirror and coupled
        groups, with ``boundary`` (e.g. :meth:`offline.dataset.fem_problem.FemSkin.dirichlet`)."""
        names = head.actuator_names
        index = {n: i for i, n in enumerate(names)}
        together, coupled = [], []
        for g in head.groups:
            idx = tuple(index[a] for a in g.actuators)
            if g.kind in ("together", "mirror"):
                together.append((idx, tuple(float(x) for x in g.gains)))
            elif g.kind == "coupled":
                coupled.append((idx, float(g.max_spread)))
        return cls(names, np.array([a.min for a in head.actuators]), np.array([a.max for a in head.actuators]),
                   np.array(head.neutral_pose), boundary, tuple(together), tuple(coupled))


# ------------------------------------------------------------------------------------------------ the problem
@dataclass(frozen=True, eq=False)
class ActuationProblem:
    """Mesh (its rest shape), material, actuation space, matching region (node indices) and weights."""

    mesh: TetMesh
    material: Material
    space: ActuationSpace
    region: np.ndarray
    limit_weight: float = 1.0
    limit_margin: float = 0.02
    spread_weight: float = 1e3
    length_scale: float = 1e-3
    solver: SolverOptions = field(default_factory=lambda: SolverOptions(tol_force=1e-9))
    strain: StrainConstraint | None = None

    def __post_init__(self) -> None:
        region = np.asarray(self.region, dtype=np.int64).reshape(-1)
        if region.size == 0 or region.min() < 0 or region.max() >= self.mesh.n_nodes:
            raise ValueError(f"region must be non-empty node indices in [0, {self.mesh.n_nodes})")
        if not 0 <= self.limit_margin < 0.5:
            raise ValueError(f"limit_margin must be in [0, 0.5), got {self.limit_margin}")
        object.__setattr__(self, "region", region)
        object.__setattr__(self, "_cache", {})

    def with_mesh(self, mesh: TetMesh) -> ActuationProblem:
        """The same problem on another rest shape (same topology and attachments, e.g. a new thickness).

        A strain constraint is kept: its surface must keep its rest geometry (the thickness design moves only the
        inner surface), checked here."""
        from dataclasses import replace

        if self.strain is not None:
            moved = np.abs(np.asarray(mesh.nodes)[self.strain.nodes] - self.strain.surface.rest).max()
            if moved > 1e-9:
                raise ValueError(f"the strain-constrained surface moved by {moved:.3g} m in the new rest shape; "
                                 "build the constraint on the new mesh")
        return replace(self, mesh=mesh)

    def sparse_solver(self):
        """One sparse solver object per problem: the symbolic factorization of K_ff is analysed once."""
        if "solver" not in self._cache:
            self._cache["solver"] = make_solver(self.solver.backend)
        return self._cache["solver"]


def _scale(problem: ActuationProblem) -> float:
    return 1.0 / (problem.region.size * problem.length_scale ** 2)


def penalty_terms(problem: ActuationProblem, z: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Limits and spread regularization: value, gradient (Z,) and Gauss-Newton Hessian (Z, Z) in z."""
    sp_ = problem.space
    B = sp_.basis
    p = sp_.expand(z)
    rng = sp_.hi - sp_.lo
    u = (p - sp_.lo) / rng
    m = problem.limit_margin
    under, over = np.maximum(0.0, m - u), np.maximum(0.0, u - 1.0 + m)
    w = problem.limit_weight
    val = w * float(np.sum(under ** 2 + over ** 2))
    gp = 2.0 * w * (over - under) / rng
    Hp = np.diag(2.0 * w * ((under > 0) | (over > 0)) / rng ** 2)
    for idx, spread in sp_.coupled:
        idx = list(idx)
        a, b = idx[int(np.argmax(p[idx]))], idx[int(np.argmin(p[idx]))]
        excess = p[a] - p[b] - spread
        if excess > 0:
            r2 = float(max(rng[a], rng[b])) ** 2
            val += problem.spread_weight * excess ** 2 / r2
            d = np.zeros_like(p)
            d[a], d[b] = 1.0, -1.0
            gp += 2.0 * problem.spread_weight * excess / r2 * d
            Hp += 2.0 * problem.spread_weight / r2 * np.outer(d, d)
    return val, B.T @ gp, B.T @ Hp @ B


@dataclass
class Evaluation:
    """One simulated pose: actuator values, equilibrium, objective parts."""

    z: np.ndarray
    p: np.ndarray
    x: np.ndarray
    value: float
    match: float
    strain: tuple[float, float] | None = None  # the guard's exact measure, when the problem has a constraint
    strain_penalty: float = 0.0
    strain_weight: float = 0.0  # the penalty's weight w in this value
    strain_lam: np.ndarray | None = None  # and its multipliers (K, 2)


def simulate(problem: ActuationProblem, p: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray | None:
    """Equilibrium positions (N, 3) at actuator values p (warm-started from x0, then from rest); None if no solve
    converges."""
    bc = problem.space.boundary(np.asarray(p, dtype=np.float64))
    for start in ([x0, None] if x0 is not None else [None]):
        if start is not None and _en.min_jacobian(problem.mesh, start) <= 0:
            continue
        try:
            res = solve_static(problem.mesh, problem.material, bc, x0=start, options=problem.solver)
        except (NotConverged, ValueError):
            continue
        if res.converged:
            return res.x
    return None


def evaluate(problem: ActuationProblem, z: np.ndarray, target: np.ndarray, x0: np.ndarray | None = None,
             strain_weight: float | None = None, strain_lam: np.ndarray | None = None) -> Evaluation | None:
    """Simulate at p = B z and evaluate the objective against ``target`` (R, 3); with a strain constraint, its
    penalty at weight ``strain_weight`` (default: the constraint's starting weight) and multipliers ``strain_lam``
    (default none) is part of the value."""
    p = problem.space.expand(z)
    x = simulate(problem, p, x0)
    if x is None:
        return None
    return _objective(problem, np.asarray(z, dtype=np.float64).copy(), p, x, target, strain_weight, strain_lam)


def _objective(problem: ActuationProblem, z: np.ndarray, p: np.ndarray, x: np.ndarray, target: np.ndarray,
               strain_weight: float | None, strain_lam: np.ndarray | None = None) -> Evaluation:
    match = 0.5 * _scale(problem) * float(np.sum((x[problem.region] - target) ** 2))
    value = match + penalty_terms(problem, z)[0]
    strain, pen, w = None, 0.0, 0.0
    if problem.strain is not None:
        w = problem.strain.weight if strain_weight is None else float(strain_weight)
        pen, strain = problem.strain.penalty(x, w, strain_lam)
        value += pen
    return Evaluation(z, p, x, value, match, strain, pen, w, strain_lam)


def _linearization(problem: ActuationProblem, p: np.ndarray, x: np.ndarray):
    bc, dcdp = problem.space.boundary_jacobian(p)
    K = _en.stiffness(problem.mesh, problem.material, x)
    n = K.shape[0]
    free = np.ones(n, dtype=bool)
    con = bc.dofs
    free[con] = False
    free_idx = np.flatnonzero(free)
    Kf = K[free_idx]
    Kff = Kf[:, free_idx].tocsr()
    Kfc = Kf[:, con]
    fac = problem.sparse_solver().factor(Kff)
    return fac, free_idx, con, Kfc, dcdp


def sensitivities(problem: ActuationProblem, p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """dx/dp (3N, A) at the equilibrium x of pose p (direct method: one factorization, A solves)."""
    fac, free_idx, con, Kfc, dcdp = _linearization(problem, p, x)
    dx = np.zeros((3 * problem.mesh.n_nodes, dcdp.shape[1]))
    dx[con] = dcdp
    dx[free_idx] = -fac.solve(np.asarray(Kfc @ dcdp))
    return dx


def _region_dofs(problem: ActuationProblem) -> np.ndarray:
    return (3 * problem.region[:, None] + np.arange(3)).ravel()


def adjoint_gradient(problem: ActuationProblem, ev: Evaluation, target: np.ndarray) -> np.ndarray:
    """dE/dz by one adjoint solve: K_ff λ = ∂E/∂x_f, dE/dc = ∂E/∂x_c − K_cf λ, dE/dp = dc/dpᵀ dE/dc."""
    fac, free_idx, con, Kfc, dcdp = _linearization(problem, ev.p, ev.x)
    dEdx = np.zeros(3 * problem.mesh.n_nodes)
    dEdx[_region_dofs(problem)] = _scale(problem) * (ev.x[problem.region] - target).ravel()
    if problem.strain is not None:
        r, Jr = problem.strain.jacobian(ev.x, ev.strain_weight, ev.strain_lam)
        dEdx += ev.strain_weight * np.asarray(Jr.T @ r).ravel()
    lam = fac.solve(dEdx[free_idx])
    dEdc = dEdx[con] - np.asarray(Kfc.T @ lam).ravel()
    return problem.space.basis.T @ (dcdp.T @ dEdc) + penalty_terms(problem, ev.z)[1]


def direct_gradient(problem: ActuationProblem, ev: Evaluation, target: np.ndarray) -> np.ndarray:
    """dE/dz from the direct sensitivities (what each Gauss-Newton step uses)."""
    dx = sensitivities(problem, ev.p, ev.x)
    J = dx[_region_dofs(problem)] @ problem.space.basis
    r = (ev.x[problem.region] - target).ravel()
    g = _scale(problem) * (J.T @ r) + penalty_terms(problem, ev.z)[1]
    if problem.strain is not None:
        rs, Jr = problem.strain.jacobian(ev.x, ev.strain_weight, ev.strain_lam)
        g += ev.strain_weight * (np.asarray(Jr @ dx) @ problem.space.basis).T @ rs
    return g


# ------------------------------------------------------------------------------------------------ optimizer
@dataclass
class TargetResult:
    """Actuation found for one target: values, equilibrium, objective, iterations, pose solves, log, time; with a
    strain constraint, the guard's exact measure at the result, whether it is inside the range, and the penalty
    weight that got it there."""

    p: np.ndarray
    x: np.ndarray
    value: float
    match: float
    iterations: int
    converged: bool
    solves: int
    log: list[dict]
    seconds: float
    start: str = ""
    strain: tuple[float, float] | None = None
    strain_inside: bool | None = None
    strain_weight: float = 0.0


def strain_text(res: TargetResult) -> str:
    """``, strain −a % / +b % (inside|OUTSIDE)`` for a progress line ('' without a strain constraint)."""
    if res.strain is None:
        return ""
    return f", strain {res.strain[0]:+.1%} / {res.strain[1]:+.1%} ({'inside' if res.strain_inside else 'OUTSIDE'})"


def _gauss_newton(problem: ActuationProblem, target: np.ndarray, ev: Evaluation, w: float,
                  lam: np.ndarray | None, max_iterations: int, tol_step: float, tol_value: float, log: list[dict],
                  t0: float, progress: Callable[[dict], None] | None, seen: Callable[[Evaluation], None]
                  ) -> tuple[Evaluation, int, int, bool]:
    """Projected, damped Gauss-Newton from ``ev`` at strain-penalty weight ``w`` and multipliers ``lam``: (result,
    iterations, solves, converged). ``seen`` is called with every converged trial pose."""
    space = problem.space
    rd = _region_dofs(problem)
    s = _scale(problem)
    zr = space.zhi - space.zlo
    mu = 1e-6
    converged = False
    solves = 0
    it = 0
    it0 = log[-1]["iteration"] if log else 0
    for it in range(1, max_iterations + 1):
        dx = sensitivities(problem, ev.p, ev.x)
        J = np.sqrt(s) * (dx[rd] @ space.basis)
        r = np.sqrt(s) * (ev.x[problem.region] - target).ravel()
        if problem.strain is not None:
            rs, Jr = problem.strain.jacobian(ev.x, w, lam)
            if rs.size:
                J = np.vstack([J, np.sqrt(w) * (np.asarray(Jr @ dx) @ space.basis)])
                r = np.concatenate([r, np.sqrt(w) * rs])
        _, gpen, Hpen = penalty_terms(problem, ev.z)
        g = J.T @ r + gpen
        H = J.T @ J + Hpen
        held = ((ev.z <= space.zlo + 1e-12 * zr) & (g > 0)) | ((ev.z >= space.zhi - 1e-12 * zr) & (g < 0))
        H[held, :] = 0.0
        H[:, held] = 0.0
        H[held, held] = 1.0
        g_act = np.where(held, 0.0, g)
        if not np.any(g_act):
            converged = True
            break
        new = None
        for _ in range(12):
            D = np.diag(np.maximum(np.diag(H), 1e-12 * max(np.trace(H), 1e-300) / len(g)))
            step = np.linalg.solve(H + mu * D, -g_act)
            z_t = space.project(ev.z + step)
            if np.max(np.abs(z_t - ev.z) / zr) < 0.1 * tol_step:
                break
            trial = evaluate(problem, z_t, target, ev.x, strain_weight=w, strain_lam=lam)
            solves += 1
            if trial is not None:
                seen(trial)
            if trial is not None and trial.value < ev.value:
                new = trial
                break
            mu = max(10.0 * mu, 1e-8)
        if new is None:
            converged = True
            break
        mu = max(mu / 3.0, 1e-9)
        dz = float(np.max(np.abs(new.z - ev.z) / zr))
        decrease = ev.value - new.value
        old = ev.value
        ev = new
        entry = {"iteration": it0 + it, "objective": ev.value, "match": ev.match, "step_max": dz,
                 "seconds": time.perf_counter() - t0}
        if ev.strain is not None:
            entry.update(strain_min=ev.strain[0], strain_max=ev.strain[1], strain_weight=w)
        log.append(entry)
        if progress is not None:
            progress(entry)
        if dz < tol_step or decrease < tol_value * old:
            converged = True
            break
    return ev, it, solves, converged


def optimize_target(problem: ActuationProblem, target: np.ndarray, p0: np.ndarray, x0: np.ndarray | None = None,
                    *, max_iterations: int = 30, tol_step: float = 1e-5, tol_value: float = 1e-6,
                    start_eval: Evaluation | None = None, progress: Callable[[dict], None] | None = None,
                    strain_weight: float | None = None) -> TargetResult:
    """Projected, damped Gauss-Newton on E(z) for one target (R, 3), from actuator values p0.

    Stops when no actuator moves by more than ``tol_step`` of its range, or the objective's relative decrease is
    below ``tol_value``, or no step decreases it. Variables at a limit whose gradient pushes outward are held.
    With a strain constraint (``problem.strain``) its hinge residuals are Gauss-Newton rows; when the exact measure
    at the optimum is still outside the range, the weight grows by the constraint's ``growth`` and the optimization
    continues from there (at most ``max_rounds`` times; ``max_iterations`` per round). ``strain_weight`` overrides
    the constraint's starting weight (e.g. the weight an earlier solution of the same target needed).
    """
    t0 = time.perf_counter()
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (problem.region.size, 3):
        raise ValueError(f"target must have shape ({problem.region.size}, 3), got {target.shape}")
    space = problem.space
    con = problem.strain
    w = (con.weight if strain_weight is None else float(strain_weight)) if con is not None else 0.0
    lam = None
    solves = 0
    ev = start_eval
    if ev is not None and con is not None and (ev.strain_weight != w or ev.strain_lam is not None):
        ev = _objective(problem, ev.z, ev.p, ev.x, target, w)
    if ev is None:
        ev = evaluate(problem, space.project(space.reduce(p0)), target, x0, strain_weight=w)
        solves += 1
        if ev is None:
            raise ValueError("the starting actuation does not give a converged FEM pose")
    best: list[Evaluation] = []  # the best pose seen whose exact measure is inside the range (by match)

    def seen(e: Evaluation) -> None:
        if con is not None and con.inside(e.strain) and (not best or e.match < best[0].match):
            best[:] = [e]

    seen(ev)
    log = [{"iteration": 0, "objective": ev.value, "match": ev.match}]
    iterations = 0
    rounds = 0
    violation = np.inf
    while True:
        ev, it, n, converged = _gauss_newton(problem, target, ev, w, lam, max_iterations, tol_step, tol_value, log,
                                             t0, progress, seen)
        iterations += it
        solves += n
        if con is None or rounds >= con.max_rounds:
            break
        v = con.violation(ev.x)
        if con.inside(ev.strain):
            break  # the exact measure is inside the range
        # augmented Lagrangian round: multiplier update; weight growth when the violation did not shrink enough
        rounds += 1
        lam = con.multipliers(ev.x, w, lam)
        if v > 0.25 * violation:
            w = min(w * con.growth, con.max_weight)
        violation = v
        ev = _objective(problem, ev.z, ev.p, ev.x, target, w, lam)
    if con is not None and not con.inside(ev.strain) and best:
        ev = best[0]  # the optimum left the range: the best pose seen inside it
    elif con is not None and best and best[0].match < ev.match:
        ev = best[0]
    res = TargetResult(ev.p, ev.x, ev.value, ev.match, iterations, converged, solves, log, time.perf_counter() - t0)
    if con is not None:
        res.strain, res.strain_inside, res.strain_weight = ev.strain, con.inside(ev.strain), w
    return res


def pull_back(problem: ActuationProblem, ev: Evaluation, target: np.ndarray, steps: int = 6) -> Evaluation | None:
    """The pose on the straight line from neutral to ``ev.p`` furthest from neutral whose strain lies within the
    constraint's tightened limits (bisection, ``steps`` solves), or None when none of the tried ones does."""
    con = problem.strain
    space = problem.space
    z0, z1 = space.reduce(space.neutral), ev.z
    a, b = 0.0, 1.0
    found = None
    x_prev = ev.x
    for _ in range(steps):
        t = 0.5 * (a + b)
        e = evaluate(problem, space.project(z0 + t * (z1 - z0)), target, x_prev)
        if e is not None and con.violation(e.x) == 0.0:
            a, found = t, e
        else:
            b = t
        if e is not None:
            x_prev = e.x
    return found


def optimize_targets(problem: ActuationProblem, targets: Sequence[np.ndarray], *,
                     starts: Sequence[np.ndarray | None] | None = None, previous: Sequence[TargetResult] | None = None,
                     max_iterations: int = 30, tol_step: float = 1e-5, tol_value: float = 1e-6,
                     progress: Callable[[int, dict], None] | None = None) -> list[TargetResult]:
    """Optimize each target in turn, warm-started.

    Start candidates per target: ``previous[k]`` (this target's own earlier solution, e.g. before a thickness
    change), ``starts[k]`` (e.g. the predictor's inverse), the previous target's solution, and neutral; the one with
    the lowest objective is used, and its Newton solves start from the nearest available equilibrium.
    """
    space = problem.space
    results: list[TargetResult] = []
    for k, target in enumerate(targets):
        target = np.asarray(target, dtype=np.float64)
        cands: list[tuple[str, np.ndarray, np.ndarray | None]] = []
        if previous is not None and previous[k] is not None:
            cands.append(("previous", previous[k].p, previous[k].x))
        if starts is not None and starts[k] is not None:
            cands.append(("given", np.asarray(starts[k], dtype=np.float64), results[-1].x if results else None))
        if results:
            cands.append(("last target", results[-1].p, results[-1].x))
        cands.append(("neutral", space.neutral, None))
        w = None
        if problem.strain is not None and previous is not None and previous[k] is not None:
            w = float(np.clip(previous[k].strain_weight, problem.strain.weight, problem.strain.max_weight))
        best: tuple[str, Evaluation] | None = None
        solves = 0
        for name, p, x in cands:
            ev = evaluate(problem, space.project(space.reduce(p)), target, x, strain_weight=w)
            solves += 1
            if ev is not None and (best is None or ev.value < best[1].value):
                best = (name, ev)
        if best is None:
            raise RuntimeError(f"target {k}: no starting actuation gives a converged FEM pose")
        if problem.strain is not None and problem.strain.violation(best[1].x) > 0:
            back = pull_back(problem, best[1], target)  # start inside the constraint
            solves += 6
            if back is not None:
                best = (f"{best[0]}, pulled back", back)

        def report(entry: dict, k: int = k) -> None:
            if progress is not None:
                progress(k, entry)

        res = optimize_target(problem, target, best[1].p, best[1].x, max_iterations=max_iterations,
                              tol_step=tol_step, tol_value=tol_value, start_eval=best[1], progress=report,
                              strain_weight=w)
        res.solves += solves
        res.start = best[0]
        results.append(res)
    return results
