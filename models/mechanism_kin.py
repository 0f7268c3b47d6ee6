"""Kinematics of a :class:`~models.mechanism_file.MechanismSpec`: the closure constraints c(s) = 0 and their solution.

Every moving body carries six coordinates: its rigid transform from the neutral configuration (``x' = R x + t``),
updated as ``R ← exp(δw) R``, ``t ← t + δt``. Joints, couplers and the motors' joint values are constraints on these
coordinates, written in the head frame with analytic Jacobians. The bodies split into independent groups (each
connected through joints and couplers, ground aside); each group is solved by Newton's method from its previous
solution, stepping the motor values in small increments (halved where the tangent predicts a long move) so the
solution stays on its assembly branch.
:func:`state_derivatives` gives d(state)/d(motor values) and d(state)/d(design parameters) by implicit
differentiation (``J_s ds = -∂c/∂θ dθ``). Model (spec) and work data (:class:`State`) are kept apart, as in
pinocchio.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from models.errors import LikenessError
from models.mechanism_file import Coupler, Joint, MechanismSpec, get_param, with_params
from models.rigid import matrix_to_rotvec, rotvec_to_matrix

EYE3 = np.eye(3)
#: Newton converges when every residual is below this (m or rad).
RESIDUAL_TOL = 1e-11
#: Largest joint-value step of the continuation (rad for revolute, m for prismatic joints).
STEP = {"revolute": 0.5, "prismatic": 0.03}
#: Longest predictor step of the continuation (rad or m per body coordinate); longer: the joint-value step is halved.
PREDICT_MAX = 0.5


class AssemblyError(LikenessError, ValueError):
    """A linkage cannot assemble at the requested motor values; names the loop and the motor values. ``bodies``: the
    loop's bodies, for a caller that changes only what that loop depends on."""

    def __init__(self, message: str, bodies: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.bodies = tuple(bodies)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product of two 3-vectors (numpy's general ``cross`` costs ten times more on one pair)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``n`` to a right-handed frame (e1 × e2 = n)."""
    ref = EYE3[int(np.argmin(np.abs(n)))]
    e1 = _cross(n, ref)
    e1 /= math.sqrt(float(e1 @ e1))
    return e1, _cross(n, e1)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _dlog(r: np.ndarray) -> np.ndarray:
    """d log(exp(δ) exp(r))/dδ at δ = 0: the inverse left Jacobian of SO(3) at the rotation vector ``r``."""
    th = math.sqrt(float(r @ r))
    x, y, z = r
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    c = 1.0 / 12.0 if th < 1e-6 else 1.0 / th**2 - (1.0 + math.cos(th)) / (2.0 * th * math.sin(th))
    return EYE3 - 0.5 * K + c * (K @ K)


def _point_jac(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """d(R p + t)/d[δt, δw] for a point fixed to a body, (3, 6)."""
    x, y, z = R @ p
    return np.array([[1.0, 0.0, 0.0, 0.0, z, -y], [0.0, 1.0, 0.0, -z, 0.0, x], [0.0, 0.0, 1.0, y, -x, 0.0]])


# ---------------------------------------------------------------------------- constraints
@dataclass(frozen=True)
class Constraint:
    """One joint or coupler, with the motor's joint value when it is driven: rows of c(s) between bodies a and b."""

    name: str
    kind: str  # the joint or coupler kind
    a: int  # body index, -1 for the ground
    b: int
    item: Joint | Coupler
    motor: str | None = None

    def rows(self) -> int:
        base = {"revolute": 5, "prismatic": 5, "spherical": 3, "fixed": 6, "rod": 1, "gear": 1}[self.kind]
        return base + (self.motor is not None)


def _revolute(j: Joint, Ra, ta, Rb, tb, target):
    p, n = j.anchor, j.axis
    e1, e2 = _basis(n)
    m = 6 if target is not None else 5
    r, Ja, Jb = np.zeros(m), np.zeros((m, 6)), np.zeros((m, 6))
    r[:3] = (Rb @ p + tb) - (Ra @ p + ta)
    Jb[:3], Ja[:3] = _point_jac(Rb, p), -_point_jac(Ra, p)
    bn, ae1, ae2 = Rb @ n, Ra @ e1, Ra @ e2
    for i, ae in ((3, ae1), (4, ae2)):
        r[i] = bn @ ae
        Jb[i, 3:] = _cross(bn, ae)
        Ja[i, 3:] = -Jb[i, 3:]
    if target is not None:
        be1 = Rb @ e1
        x, y = be1 @ ae1, be1 @ ae2
        r[5] = _wrap(math.atan2(y, x) - target)
        h = x * x + y * y
        Jb[5, 3:] = (x * _cross(be1, ae2) - y * _cross(be1, ae1)) / h
        Ja[5, 3:] = (x * _cross(ae2, be1) - y * _cross(ae1, be1)) / h
    return r, Ja, Jb


def revolute_angle(j: Joint, Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle of a revolute joint: the child's turn about the axis relative to the parent (rad)."""
    e1, e2 = _basis(j.axis)
    be1 = Rb @ e1
    return math.atan2(be1 @ (Ra @ e2), be1 @ (Ra @ e1))


def _prismatic(j: Joint, Ra, ta, Rb, tb, target):
    c, d = j.anchor, j.axis
    e1, e2 = _basis(d)
    m = 6 if target is not None else 5
    r, Ja, Jb = np.zeros(m), np.zeros((m, 6)), np.zeros((m, 6))
    delta = (Rb @ c + tb) - (Ra @ c + ta)
    Db, Da = _point_jac(Rb, c), -_point_jac(Ra, c)
    ad = Ra @ d
    s = float(ad @ delta)
    Js_b, Js_a = ad @ Db, ad @ Da
    Js_a[3:] += _cross(ad, delta)
    for i, e in ((0, e1), (1, e2)):
        ae = Ra @ e
        r[i] = ae @ delta
        Jb[i], Ja[i] = ae @ Db, ae @ Da
        Ja[i, 3:] += _cross(ae, delta)
    Rt = rotvec_to_matrix(j.tilt_axis * j.tilt_rate * s) if j.tilt_axis is not None else EYE3
    E = Rb @ (Ra @ Rt).T
    r[2:5] = matrix_to_rotvec(E)
    L = _dlog(r[2:5])
    Jb[2:5, 3:], Ja[2:5, 3:] = L, -L @ E
    if j.tilt_axis is not None:
        k = L @ (Rb @ j.tilt_axis) * j.tilt_rate
        Jb[2:5] -= np.outer(k, Js_b)
        Ja[2:5] -= np.outer(k, Js_a)
    if target is not None:
        r[5] = s - target
        Jb[5], Ja[5] = Js_b, Js_a
    return r, Ja, Jb


def prismatic_travel(j: Joint, Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> float:
    """The travel of a prismatic joint along its axis (m)."""
    return float((Ra @ j.axis) @ ((Rb @ j.anchor + tb) - (Ra @ j.anchor + ta)))


def _spherical(j: Joint, Ra, ta, Rb, tb, target):
    p = j.anchor
    return (Rb @ p + tb) - (Ra @ p + ta), -_point_jac(Ra, p), _point_jac(Rb, p)


def _fixed(j: Joint, Ra, ta, Rb, tb, target):
    r, Ja, Jb = np.zeros(6), np.zeros((6, 6)), np.zeros((6, 6))
    r[:3], Ja[:3], Jb[:3] = _spherical(j, Ra, ta, Rb, tb, None)
    E = Rb @ Ra.T
    r[3:] = matrix_to_rotvec(E)
    L = _dlog(r[3:])
    Jb[3:, 3:], Ja[3:, 3:] = L, -L @ E
    return r, Ja, Jb


def _rod(c: Coupler, Ra, ta, Rb, tb, target):
    d = (Ra @ c.a_point + ta) - (Rb @ c.b_point + tb)
    L = float(np.linalg.norm(d))
    u = d / L
    return np.array([L - c.length]), (u @ _point_jac(Ra, c.a_point))[None], -(u @ _point_jac(Rb, c.b_point))[None]


def _turn(R: np.ndarray, n: np.ndarray) -> tuple[float, np.ndarray]:
    """A body's turn about the fixed axis ``n`` (rad) and its derivative with respect to δw."""
    e1, e2 = _basis(n)
    be1 = R @ e1
    x, y = be1 @ e1, be1 @ e2
    return math.atan2(y, x), (x * _cross(be1, e2) - y * _cross(be1, e1)) / (x * x + y * y)


def _gear(c: Coupler, Ra, ta, Rb, tb, target):
    tha, ga = _turn(Ra, c.axis)
    thb, gb = _turn(Rb, c.axis)
    Ja, Jb = np.zeros((1, 6)), np.zeros((1, 6))
    Ja[0, 3:], Jb[0, 3:] = -c.ratio * ga, gb
    return np.array([thb - c.ratio * tha]), Ja, Jb


_EVAL = {"revolute": _revolute, "prismatic": _prismatic, "spherical": _spherical, "fixed": _fixed, "rod": _rod,
         "gear": _gear}


# ---------------------------------------------------------------------------- structure
@dataclass(frozen=True)
class Group:
    """Bodies that move together through joints and couplers (ground aside), their constraints and motors."""

    bodies: tuple[int, ...]
    constraints: tuple[Constraint, ...]
    motors: tuple[str, ...]

    @property
    def size(self) -> int:
        return 6 * len(self.bodies)


@dataclass(frozen=True)
class Structure:
    """The index of moving bodies and their independent groups, built once per spec."""

    spec: MechanismSpec
    bodies: tuple[str, ...]  # moving bodies (not the ground)
    groups: tuple[Group, ...]

    def index(self, body: str) -> int:
        return -1 if body == self.spec.ground else self.bodies.index(body)


def structure(spec: MechanismSpec) -> Structure:
    """Split the moving bodies into independent groups and list each group's constraints."""
    bodies = tuple(n for n in spec.bodies if n != spec.ground)
    idx = {n: i for i, n in enumerate(bodies)}
    idx[spec.ground] = -1
    parent = list(range(len(bodies)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    motor_of = {m.joint: m.name for m in spec.motors.values()}
    cons: list[Constraint] = []
    for j in spec.joints.values():
        cons.append(Constraint(j.name, j.kind, idx[j.parent], idx[j.child], j, motor_of.get(j.name)))
    for c in spec.couplers.values():
        cons.append(Constraint(c.name, c.kind, idx[c.a], idx[c.b], c))
    for c in cons:
        if c.a >= 0 and c.b >= 0:
            parent[find(c.a)] = find(c.b)
    roots: dict[int, list[int]] = {}
    for i in range(len(bodies)):
        roots.setdefault(find(i), []).append(i)
    groups = []
    for members in roots.values():
        mset = set(members)
        gc = tuple(c for c in cons if c.a in mset or c.b in mset)
        groups.append(Group(tuple(members), gc, tuple(c.motor for c in gc if c.motor is not None)))
    return Structure(spec, bodies, tuple(groups))


# ---------------------------------------------------------------------------- state and residuals
@dataclass
class State:
    """Work data: each moving body's rotation ``R`` (n, 3, 3) and translation ``t`` (n, 3) from neutral."""

    R: np.ndarray
    t: np.ndarray

    @classmethod
    def neutral(cls, n: int) -> State:
        return cls(np.repeat(EYE3[None], n, axis=0), np.zeros((n, 3)))

    def copy(self) -> State:
        return State(self.R.copy(), self.t.copy())

    def transform(self, i: int) -> np.ndarray:
        """4x4 transform of moving body ``i`` from neutral (identity for the ground, ``i = -1``)."""
        T = np.eye(4)
        if i >= 0:
            T[:3, :3], T[:3, 3] = self.R[i], self.t[i]
        return T


def _body(state: State, i: int) -> tuple[np.ndarray, np.ndarray]:
    return (EYE3, np.zeros(3)) if i < 0 else (state.R[i], state.t[i])


def group_residual(group: Group, state: State, targets: Mapping[str, float],
                   jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """c(s) of one group and its Jacobian with respect to the group's body coordinates [δt, δw] per body."""
    col = {b: 6 * k for k, b in enumerate(group.bodies)}
    rs, rows = [np.zeros(0)], [np.zeros((0, group.size))]
    for c in group.constraints:
        Ra, ta = _body(state, c.a)
        Rb, tb = _body(state, c.b)
        r, Ja, Jb = _EVAL[c.kind](c.item, Ra, ta, Rb, tb, None if c.motor is None else targets[c.motor])
        rs.append(r)
        if jacobian:
            J = np.zeros((r.size, group.size))
            if c.a >= 0:
                J[:, col[c.a]:col[c.a] + 6] += Ja
            if c.b >= 0:
                J[:, col[c.b]:col[c.b] + 6] += Jb
            rows.append(J)
    return np.concatenate(rs), (np.vstack(rows) if jacobian else None)


def _apply(group: Group, state: State, dx: np.ndarray) -> None:
    for k, b in enumerate(group.bodies):
        state.t[b] += dx[6 * k:6 * k + 3]
        state.R[b] = rotvec_to_matrix(dx[6 * k + 3:6 * k + 6]) @ state.R[b]


def _step(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The Newton step: a square solve, least squares where constraints are redundant or singular."""
    if J.shape[0] == J.shape[1]:
        try:
            return np.linalg.solve(J, -r)
        except np.linalg.LinAlgError:
            pass
    return np.linalg.lstsq(J, -r, rcond=None)[0]


def newton(group: Group, state: State, targets: Mapping[str, float], iterations: int = 30) -> bool:
    """Newton (least squares where constraints are redundant) on one group, in place; True when c(s) = 0."""
    for _ in range(iterations):
        r, J = group_residual(group, state, targets)
        if np.max(np.abs(r)) < RESIDUAL_TOL:
            return True
        dx = _step(J, r)
        if not np.all(np.isfinite(dx)) or np.max(np.abs(dx)) > 1.0:
            return False
        _apply(group, state, dx)
    r, _ = group_residual(group, state, targets, jacobian=False)
    return bool(np.max(np.abs(r)) < RESIDUAL_TOL * 100)


def joint_targets(spec: MechanismSpec, motors: Mapping[str, float]) -> dict[str, float]:
    """Each motor's joint value (ratio × motor value, SI) for these motor values (missing motors: zero)."""
    return {n: m.ratio * float(motors.get(n, 0.0)) for n, m in spec.motors.items()}


def solve_group(st: Structure, group: Group, state: State, start: Mapping[str, float],
                goal: Mapping[str, float]) -> None:
    """Move ``group`` in ``state`` from its solution at joint values ``start`` to ``goal`` by continuation."""
    spec = st.spec
    span = max((abs(goal[m] - start[m]) / STEP[spec.joints[spec.motors[m].joint].kind] for m in group.motors),
               default=0.0)
    steps = max(1, math.ceil(span))
    done, frac, depth = 0.0, 1.0 / steps, 0
    while done < 1.0 - 1e-12:
        nxt = min(1.0, done + frac)
        trial = state.copy()
        here = {m: start[m] + done * (goal[m] - start[m]) for m in group.motors}
        tg = {m: start[m] + nxt * (goal[m] - start[m]) for m in group.motors}
        if _predict(group, trial, here, tg) and newton(group, trial, tg):
            state.R[:], state.t[:] = trial.R, trial.t
            done = nxt
            continue
        depth += 1
        frac /= 2
        if depth > 8:
            raise _assembly_error(st, group, goal, tg)


def _predict(group: Group, state: State, here: Mapping[str, float], goal: Mapping[str, float]) -> bool:
    """Euler predictor of the continuation: move along the solution's tangent d(state)/d(joint values). False (state
    untouched) when the tangent step is too long (0.5 rad or m): a corrector started that far from the solution may
    settle on another assembly branch, so the caller takes a shorter step instead."""
    _, J = group_residual(group, state, here)
    dc = np.zeros(J.shape[0])
    row = 0
    for c in group.constraints:
        row += c.rows()
        if c.motor is not None:
            dc[row - 1] = -(goal[c.motor] - here[c.motor])
    dx = _step(J, dc)
    if not np.all(np.isfinite(dx)):  # a singular tangent: Newton alone from here
        return True
    if np.max(np.abs(dx)) >= PREDICT_MAX:
        return False
    _apply(group, state, dx)
    return True


def _assembly_error(st: Structure, group: Group, goal: Mapping[str, float], at: Mapping[str, float]) -> AssemblyError:
    spec = st.spec
    names = [st.bodies[b] for b in group.bodies]
    rods = [c.name for c in group.constraints if c.kind in ("rod", "gear")]

    def show(values: Mapping[str, float]) -> str:
        out = []
        for m in group.motors:
            mt = spec.motors[m]
            v = values[m] / mt.ratio
            kind = spec.joints[mt.joint].kind
            out.append(f"{m}={math.degrees(v):.3f} deg" if kind == "revolute" else f"{m}={v * 1e3:.3f} mm")
        return ", ".join(out)

    return AssemblyError(f"{spec.source}: the loop of {', '.join(names)} (couplers {', '.join(rods) or 'none'}) "
                         f"cannot assemble at motor values {show(goal)}: Newton fails at {show(at)} (a rod too "
                         "short or too long there, or a dead point)", bodies=tuple(names))


# ---------------------------------------------------------------------------- checks and derivatives
def free_bodies(spec: MechanismSpec) -> tuple[list[str], int] | None:
    """Bodies that can still move at neutral with every motor held (the rank defect of c's Jacobian), or None."""
    st = structure(spec)
    state = State.neutral(len(st.bodies))
    targets = joint_targets(spec, {})
    free: list[str] = []
    dof = 0
    for g in st.groups:
        _, J = group_residual(g, state, targets)
        sv = np.linalg.svd(J, compute_uv=False) if J.shape[0] else np.zeros(0)
        rank = int(np.sum(sv > 1e-9 * max(1.0, sv.max(initial=0.0))))
        if rank < g.size:
            _, _, Vt = np.linalg.svd(J if J.shape[0] else np.zeros((1, g.size)))
            null = Vt[rank:]
            dof += g.size - rank
            for k, b in enumerate(g.bodies):
                if np.abs(null[:, 6 * k:6 * k + 6]).max() > 1e-6:
                    free.append(st.bodies[b])
    return (free, dof) if free else None


def body_jacobian(st: Structure, state: State, body: str, dx: np.ndarray, group: Group) -> np.ndarray:
    """d[frame origin position; rotation] of ``body`` from group-coordinate derivatives ``dx`` (size, k) → (6, k)."""
    i = st.index(body)
    if i < 0 or i not in group.bodies:
        return np.zeros((6, dx.shape[1]))
    k = group.bodies.index(i)
    block = dx[6 * k:6 * k + 6]
    origin = st.spec.bodies[body].origin
    return np.vstack([_point_jac(state.R[i], origin) @ block, block[3:]])


def motor_columns(group: Group, rows: int) -> np.ndarray:
    """∂c/∂(joint values of ``group.motors``), shape (rows, motors): each actuated constraint's last row is its joint
    value minus the motor's, so that entry is −1."""
    dc_dq = np.zeros((rows, len(group.motors)))
    row = 0
    for c in group.constraints:
        n = c.rows()
        if c.motor is not None:
            dc_dq[row + n - 1, group.motors.index(c.motor)] = -1.0
        row += n
    return dc_dq


def state_derivatives(st: Structure, group: Group, state: State, targets: Mapping[str, float],
                      params: Sequence[str] = (), h: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Implicit derivatives of the group's coordinates at a solution: (d/d joint values of ``group.motors``,
    d/d ``params``), shapes (size, motors) and (size, params). ∂c/∂θ is a central difference of c at fixed s."""
    r, J = group_residual(group, state, targets)
    pinv = np.linalg.pinv(J)
    dc_dq = motor_columns(group, r.size)
    dc_dp = np.zeros((r.size, len(params)))
    for k, p in enumerate(params):
        if p.startswith("motors."):
            raise KeyError(f"{p}: a motor ratio scales the joint value, not c(s); differentiate the motor value")
        v = get_param(st.spec, p)
        rp = _with(st, group, {p: v + h})
        rm = _with(st, group, {p: v - h})
        dc_dp[:, k] = (group_residual(rp, state, targets, jacobian=False)[0]
                       - group_residual(rm, state, targets, jacobian=False)[0]) / (2 * h)
    return -pinv @ dc_dq, -pinv @ dc_dp


def _with(st: Structure, group: Group, values: Mapping[str, float]) -> Group:
    """The group with its constraints' items taken from the spec with these parameters set."""
    spec = with_params(st.spec, values)
    items: dict[str, Joint | Coupler] = {**spec.joints, **spec.couplers}
    return Group(group.bodies, tuple(Constraint(c.name, c.kind, c.a, c.b, items[c.name], c.motor)
                                     for c in group.constraints), group.motors)
