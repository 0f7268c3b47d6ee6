"""Link-layout design: the mechanism's design variables θ and every target's actuation z_k optimized together, so
the FEM-simulated skin reaches the targets with every pose inside the validated strain range.

Objective (the actuation objective of :mod:`offline.design.actuation`, summed over targets, plus a small pull
toward the current design so that parameters nothing needs stay put):

    F(θ, z_1..z_K) = Σ_k E_k(z_k; θ) + ½ ρ Σ_i (θ_i / s_i)²

E_k is the match, limit and strain-penalty terms of target k with the attachments moved by the redesigned
mechanism (:class:`DesignBoundary`). Steps are projected, Levenberg-Marquardt-damped Gauss-Newton on all variables
at once: per target one factorization of K_ff gives dx/dp (dc/dp by central differences of the mechanism) and
dx/dθ = −K_ff⁻¹ K_fc dc/dθ (dc/dθ from the mechanism's implicit derivatives,
:mod:`offline.design.mechanism_design_kin`). Trial points are projected into the envelope (balls and boxes,
:mod:`offline.design.mechanism_design_envelope`) and the actuators' limits; a trial is kept only when F decreases
(the damping grows otherwise: a trust region in effect). A target whose pose leaves the strain range gets its
penalty weight raised tenfold (up to the constraint's maximum) at the next iteration.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from models.mechanism_kin import AssemblyError
from offline.fem import energy as _en
from offline.fem.solve import SolverOptions, rigid_transform_dirichlet

from .actuation import ActuationProblem, ActuationSpace, Evaluation, _objective, evaluate, penalty_terms
from .face import FaceSkin
from .mechanism_design_envelope import CONTINUOUS_IGNORED, DesignSpace
from .mechanism_design_kin import DesignedMechanism, points_derivative

CHECKPOINT = "layout_checkpoint.npz"


class DesignBoundary:
    """The Dirichlet conditions c(p, θ) of a face skin driven by a redesigned mechanism (callable as an
    :class:`offline.design.actuation.ActuationSpace` boundary), and dc/dθ."""

    def __init__(self, face: FaceSkin, space: DesignSpace, theta: np.ndarray | None = None) -> None:
        self.skin = face.skin
        self.space = space
        self.names = tuple(self.skin.head.actuator_names)
        self.X = np.asarray(self.skin.mesh.nodes, dtype=np.float64)
        self.offset = np.asarray(self.skin.frame_offset, dtype=np.float64)
        self.set_design(np.zeros(space.size) if theta is None else theta)

    def set_design(self, theta: np.ndarray) -> None:
        """Rebuild the mechanism at design θ; AssemblyError when a linkage cannot assemble anywhere in its motors'
        range (a design that works at the targets' poses but locks or comes apart elsewhere is no design)."""
        dm = DesignedMechanism(self.space, theta)
        if np.any(dm.theta):
            head = self.skin.head
            dm.check_range({a.name: a.min for a in head.actuators}, {a.name: a.max for a in head.actuators})
        self.dm = dm

    @property
    def theta(self) -> np.ndarray:
        return self.dm.theta

    def _values(self, p: np.ndarray) -> dict[str, float]:
        return dict(zip(self.names, (float(v) for v in p), strict=True))

    def transforms(self, p: np.ndarray) -> dict[str, np.ndarray]:
        """Each moving link's rigid motion at actuator values p, in the mesh frame."""
        T = self.dm.transforms(self._values(p))
        if np.any(self.offset):
            fwd, back = np.eye(4), np.eye(4)
            fwd[:3, 3], back[:3, 3] = self.offset, -self.offset
            T = {n: back @ t @ fwd for n, t in T.items()}
        return T

    def __call__(self, p: np.ndarray):
        T = self.transforms(p)
        moves = {self.skin.moving[n]: T[n] for n in self.skin.moving if n in T}
        return rigid_transform_dirichlet(self.skin.mesh, moves, fixed_sets=[self.skin.spec.skull_set])

    def design_jacobian(self, p: np.ndarray) -> np.ndarray:
        """dc/dθ (C, D) in the order of ``self(p).dofs``."""
        bc = self(p)
        ld = self.dm.link_derivatives(self._values(p))
        n = self.X.shape[0]
        dX = np.zeros((n, 3, self.space.size))
        taken = np.zeros(n, dtype=bool)
        for link, node_set in self.skin.moving.items():
            idx = np.asarray(self.skin.mesh.node_sets[node_set])
            idx = idx[~taken[idx]]
            if idx.size and link in ld:
                dX[idx] = points_derivative(*ld[link], self.X[idx] + self.offset)
            taken[idx] = True
        return dX.reshape(3 * n, -1)[bc.dofs]


@dataclass(frozen=True)
class LayoutSettings:
    """Layout-design settings: Gauss-Newton iterations, the pull toward the current design ρ, the stopping tolerance
    (relative decrease of F over an iteration) and the actuation iterations of the before/after stages."""

    iterations: int = 25
    regularization: float = 1e-3
    tol: float = 1e-3
    actuation_iterations: int = 12
    strain_margin: float = 0.01
    tol_force: float = 1e-8


@dataclass
class Linearization:
    """One target's residuals and Jacobians at the current point: r (m,), J_z (m, Z), J_θ (m, D)."""

    r: np.ndarray
    Jz: np.ndarray
    Jt: np.ndarray


def _scale(problem: ActuationProblem) -> float:
    return 1.0 / (problem.region.size * problem.length_scale ** 2)


class LayoutProblem:
    """The joint problem: targets, the design boundary, the actuation problem on it, the design space."""

    def __init__(self, face: FaceSkin, targets: Sequence[np.ndarray], space: DesignSpace,
                 settings: LayoutSettings = LayoutSettings(), strain: bool = True) -> None:
        from .strain_constraint import face_strain_constraint

        self.face = face
        self.targets = [np.asarray(t, dtype=np.float64) for t in targets]
        self.space = space
        self.settings = settings
        self.boundary = DesignBoundary(face, space)
        self.aspace = ActuationSpace.from_head(face.skin.head, self.boundary)
        opts = SolverOptions(backend=face.skin.spec.backend, tol_force=settings.tol_force, max_iterations=60,
                             load_steps=1)
        con = face_strain_constraint(face, margin=settings.strain_margin)
        self.measure = con  # the guard's measure, reported whether or not it constrains the poses
        con = con if strain else None
        self.problem = ActuationProblem(face.mesh, face.skin.material, self.aspace, face.outer, solver=opts,
                                        strain=con)

    def regularization(self, theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """½ρ Σ(θ/s)²: value, gradient, Hessian (diagonal)."""
        rho, s = self.settings.regularization, self.space.scale
        return (0.5 * rho * float(np.sum((theta / s) ** 2)), rho * theta / s ** 2, rho / s ** 2)

    def evaluate_all(self, theta: np.ndarray, Z: np.ndarray, X: Sequence[np.ndarray | None],
                     weights: np.ndarray, raise_assembly: bool = False) -> list[Evaluation] | None:
        """Every target simulated at design θ and actuation Z (None when the mechanism cannot assemble, or with
        ``raise_assembly`` its AssemblyError, or when a pose does not converge); the boundary is left at θ."""
        try:
            self.boundary.set_design(theta)
            out = []
            for k, target in enumerate(self.targets):
                ev = evaluate(self.problem, Z[k], target, X[k], strain_weight=float(weights[k]))
                if ev is None:
                    return None
                out.append(ev)
        except AssemblyError:
            if raise_assembly:
                raise
            return None
        return out

    def total(self, theta: np.ndarray, evs: Sequence[Evaluation]) -> float:
        return float(sum(e.value for e in evs)) + self.regularization(theta)[0]

    def linearize(self, ev: Evaluation, target: np.ndarray) -> Linearization:
        """Residual rows (match, strain hinge) and their Jacobians in z and θ at ``ev`` (boundary at the current θ)."""
        pr = self.problem
        bc, dcdp = self.aspace.boundary_jacobian(ev.p)
        dcdt = self.boundary.design_jacobian(ev.p)
        K = _en.stiffness(pr.mesh, pr.material, ev.x)
        n = K.shape[0]
        free = np.ones(n, dtype=bool)
        free[bc.dofs] = False
        fi = np.flatnonzero(free)
        Kf = K[fi]
        fac = pr.sparse_solver().factor(Kf[:, fi].tocsr())
        dc = np.hstack([dcdp, dcdt])
        dx = np.zeros((n, dc.shape[1]))
        dx[bc.dofs] = dc
        dx[fi] = -fac.solve(np.asarray(Kf[:, bc.dofs] @ dc))
        A = dcdp.shape[1]
        rd = (3 * pr.region[:, None] + np.arange(3)).ravel()
        s = np.sqrt(_scale(pr))
        B = self.aspace.basis
        J = [s * dx[rd]]
        r = [s * (ev.x[pr.region] - target).ravel()]
        if pr.strain is not None:
            rs, Jr = pr.strain.jacobian(ev.x, ev.strain_weight, ev.strain_lam)
            if rs.size:
                w = np.sqrt(ev.strain_weight)
                J.append(w * np.asarray(Jr @ dx))
                r.append(w * rs)
        Jall = np.vstack(J)
        return Linearization(np.concatenate(r), Jall[:, :A] @ B, Jall[:, A:])


def normal_equations(lp: LayoutProblem, theta: np.ndarray, evs: Sequence[Evaluation],
                     lins: Sequence[Linearization]) -> tuple[np.ndarray, np.ndarray]:
    """Gradient and Gauss-Newton Hessian of F in (z_1..z_K, θ) (dense)."""
    Zn = lins[0].Jz.shape[1]
    K = len(lins)
    D = lp.space.size
    n = K * Zn + D
    g = np.zeros(n)
    H = np.zeros((n, n))
    t = slice(K * Zn, n)
    for k, (ev, lin) in enumerate(zip(evs, lins, strict=True)):
        zk = slice(k * Zn, (k + 1) * Zn)
        _, gp, Hp = penalty_terms(lp.problem, ev.z)
        g[zk] += lin.Jz.T @ lin.r + gp
        g[t] += lin.Jt.T @ lin.r
        H[zk, zk] += lin.Jz.T @ lin.Jz + Hp
        H[zk, t] += lin.Jz.T @ lin.Jt
        H[t, zk] += lin.Jt.T @ lin.Jz
        H[t, t] += lin.Jt.T @ lin.Jt
    _, gr, hr = lp.regularization(theta)
    g[t] += gr
    H[t, t] += np.diag(hr)
    return g, H


@dataclass
class LayoutState:
    """Where the design stands: θ, actuation Z (K, Z), equilibria, strain weights, log, damping, iteration."""

    theta: np.ndarray
    Z: np.ndarray
    X: list[np.ndarray]
    weights: np.ndarray
    log: list[dict]
    mu: float = 1e-3
    iteration: int = 0
    done: bool = False
    seconds: float = 0.0  # time spent on this design over every invocation (resumed runs add up)
    held_back: dict[str, int] = field(default_factory=dict)  # loops whose part of a step was cut, and how often


Progress = Callable[[str], None]


def design_layout(lp: LayoutProblem, state: LayoutState, *, progress: Progress = print,
                  checkpoint: Callable[[LayoutState], None] | None = None) -> LayoutState:
    """Projected Levenberg-Marquardt Gauss-Newton on (θ, Z) from ``state`` until the relative decrease of F is
    below ``tol``, no trial decreases it, or ``iterations``; checkpointed after every accepted iteration."""
    s = lp.settings
    con = lp.problem.strain
    evs = lp.evaluate_all(state.theta, state.Z, state.X, state.weights)
    if evs is None:
        raise RuntimeError("the starting design does not give converged poses for every target")
    t0 = time.perf_counter()
    start_it = state.iteration
    while not state.done and state.iteration < s.iterations:
        it_t0 = time.perf_counter()
        if con is not None:  # targets still outside the range: a stiffer penalty
            for k, ev in enumerate(evs):
                if not con.inside(ev.strain) and state.weights[k] < con.max_weight:
                    state.weights[k] = min(state.weights[k] * con.growth, con.max_weight)
                    evs[k] = _objective(lp.problem, ev.z, ev.p, ev.x, lp.targets[k], state.weights[k])
        F = lp.total(state.theta, evs)
        lins = [lp.linearize(ev, q) for ev, q in zip(evs, lp.targets, strict=True)]
        g, H = normal_equations(lp, state.theta, evs, lins)
        state.held_back = {}
        new, F_new = _trial_step(lp, state, evs, g, H, F)
        state.iteration += 1
        elapsed = time.perf_counter() - t0
        left = (s.iterations - state.iteration) * elapsed / max(state.iteration - start_it, 1)
        if new is None:
            state.done = True
            lp.boundary.set_design(state.theta)
            progress(f"[design] it {state.iteration}: no step decreases the objective {F:.5g}; stopping")
            break
        theta_new, evs = new
        moved = float(np.max(np.abs(theta_new - state.theta) / lp.space.scale)) if lp.space.size else 0.0
        state.theta = theta_new
        state.Z = np.array([e.z for e in evs])
        state.X = [e.x for e in evs]
        match = float(sum(e.match for e in evs))
        strain = [e.strain for e in evs if e.strain is not None]
        entry = {"iteration": state.iteration, "objective": F_new, "match": match, "mu": state.mu,
                 "design_step_scaled": moved, "seconds": time.perf_counter() - it_t0,
                 "strain_min": min((a for a, _ in strain), default=None),
                 "strain_max": max((b for _, b in strain), default=None),
                 "outside": [k for k, e in enumerate(evs) if con is not None and not con.inside(e.strain)],
                 "loops_cut": dict(state.held_back)}
        state.log.append(entry)
        rel = (F - F_new) / max(abs(F), 1e-300)
        progress(f"[design] it {state.iteration}/{s.iterations} objective {F:.5g} -> {F_new:.5g} (match "
                 f"{match:.5g}, {len(entry['outside'])} pose(s) outside the strain range), design step "
                 f"{moved:.2f} scales, {entry['seconds']:.0f}s  ETA {left / 60:.1f} min"
                 + (f"; step cut where a loop would not assemble: {_cuts(state.held_back)}" if state.held_back
                    else ""))
        if rel < s.tol and not entry["outside"]:
            state.done = True
            progress(f"[design] relative decrease {rel:.2e} below {s.tol:.0e}: converged")
        if checkpoint is not None:
            checkpoint(state)
    return state


def _trial_step(lp: LayoutProblem, state: LayoutState, evs: list[Evaluation], g: np.ndarray, H: np.ndarray,
                F: float) -> tuple[tuple[np.ndarray, list[Evaluation]] | None, float]:
    """Damped steps, projected into the envelope and the limits, until one decreases F (at most 8 tries)."""
    K, Zn = state.Z.shape
    dscale = np.concatenate([np.tile(lp.aspace.zhi - lp.aspace.zlo, K), lp.space.scale])
    Hs = H * np.outer(dscale, dscale)  # scaled variables: each of order one over its range or scale
    gs = g * dscale
    diag = np.maximum(np.diag(Hs), 1e-9 * max(np.trace(Hs) / len(gs), 1e-300))
    for _ in range(8):
        step = np.linalg.solve(Hs + state.mu * np.diag(diag), -gs) * dscale
        Z_t = np.array([lp.aspace.project(state.Z[k] + step[k * Zn:(k + 1) * Zn]) for k in range(K)])
        theta_t, trial = _assembling_step(lp, state.theta, step[K * Zn:], Z_t, state)
        if trial is not None:
            F_t = lp.total(theta_t, trial)
            if F_t < F:
                state.mu = max(state.mu / 3.0, 1e-9)
                return (theta_t, trial), F_t
        state.mu = max(state.mu * 10.0, 1e-6)
    return None, F


#: Trials of one design step before it is given up (each cuts the failing loop's part of the step).
LOOP_BACKOFFS = 12


def _cuts(held: Mapping[str, int]) -> str:
    """The loops whose part of a step was cut, most often first, for the progress line."""
    return "; ".join(f"{loop} x{n}" for loop, n in sorted(held.items(), key=lambda kv: -kv[1]))


def _assembling_step(lp: LayoutProblem, theta: np.ndarray, d_theta: np.ndarray, Z_t: np.ndarray,
                     state: LayoutState) -> tuple[np.ndarray, list[Evaluation] | None]:
    """The design trial θ + d_theta, evaluated; a linkage loop that would not assemble over its motors' range has
    its own variables' part of the step cut (by 4 each time, then dropped) and the trial is made again, so one
    loop at the edge of assembling does not hold back the others' steps. θ itself assembles, so dropping every
    failing loop's part ends with a design that assembles unless LOOP_BACKOFFS trials run out first (then None, and
    the caller damps the whole step as before)."""
    factor = np.ones(lp.space.size)
    theta_t = lp.space.project(theta + d_theta)
    for _ in range(LOOP_BACKOFFS):
        try:
            return theta_t, lp.evaluate_all(theta_t, Z_t, state.X, state.weights, raise_assembly=True)
        except AssemblyError as exc:
            mask = lp.space.touching(exc.bodies)
            if not mask.any() or not np.any(factor[mask] > 0):
                return theta_t, None
            factor[mask] = np.where(factor[mask] > 1.0 / 64, factor[mask] / 4.0, 0.0)
            state.held_back[", ".join(exc.bodies)] = state.held_back.get(", ".join(exc.bodies), 0) + 1
            theta_t = lp.space.project(theta + d_theta * factor)
    return theta_t, None


# ------------------------------------------------------------------------------------------------ checkpoint
def save_checkpoint(out: Path, state: LayoutState, meta: Mapping[str, Any], extra: Mapping[str, np.ndarray]) -> None:
    """The state and the finished stages' arrays, atomically (``out/layout_checkpoint.npz``)."""
    from models.atomic import atomic_path

    out.mkdir(parents=True, exist_ok=True)
    info = {**meta, "log": state.log, "mu": state.mu, "iteration": state.iteration, "done": state.done,
            "seconds": state.seconds}
    with atomic_path(out / CHECKPOINT, suffix=".npz") as tmp:
        np.savez(tmp, meta=np.array(json.dumps(info, default=float)), theta=state.theta, Z=state.Z,
                 X=np.asarray(state.X), weights=state.weights, **extra)


def load_checkpoint(out: Path, meta: Mapping[str, Any]) -> tuple[LayoutState, dict[str, np.ndarray], dict] | None:
    """The saved state when it was made for the same targets, settings and envelope; else None."""
    path = out / CHECKPOINT
    if not path.exists():
        return None
    with np.load(path) as z:
        info = json.loads(str(z["meta"]))
        arrays = {k: np.asarray(z[k]) for k in z.files if k != "meta"}
    def same(k: str, v: Any) -> bool:
        if k == "envelope" and isinstance(info.get(k), dict):  # the continuous limits only (see CONTINUOUS_IGNORED)
            return {a: b for a, b in info[k].items() if a not in CONTINUOUS_IGNORED} == v
        return info.get(k) == v

    if not all(same(k, v) for k, v in json.loads(json.dumps(dict(meta), default=float)).items()):
        return None
    state = LayoutState(arrays.pop("theta"), arrays.pop("Z"), list(arrays.pop("X")), arrays.pop("weights"),
                        list(info["log"]), float(info["mu"]), int(info["iteration"]), bool(info["done"]),
                        float(info.get("seconds", 0.0)))
    return state, arrays, info


def settings_json(settings: LayoutSettings) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(settings)))


def with_strain_weight(problem: ActuationProblem, weight: float) -> ActuationProblem:
    """The problem with the strain penalty's starting weight set (the after stage starts where the design ended)."""
    if problem.strain is None:
        return problem
    return replace(problem, strain=replace(problem.strain, weight=float(weight)))
