"""Kinematics of a mechanism at many motor values at once: :mod:`models.mechanism_kin` vectorised over poses.

Calibration fits and link-map tabulation solve a mechanism at hundreds of motor vectors; one Python Newton per pose
spends its time in small-array overhead. Here the poses of a group are rows of stacked residuals (n, m) and
Jacobians (n, m, size), and each Newton step is one ``np.linalg.solve`` on the stacked systems. Every pose follows
the single-pose algorithm exactly (the same continuation steps, Euler predictor, tolerances and step halving), so
from the same start it lands on the same assembly branch as :func:`models.mechanism_kin.solve_group`. States are
arrays ``R`` (n, bodies, 3, 3) and ``t`` (n, bodies, 3), indexed like :class:`models.mechanism_kin.State`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from models.mechanism_file import Coupler, Joint, get_param
from models.mechanism_kin import (
    EYE3,
    PREDICT_MAX,
    RESIDUAL_TOL,
    STEP,
    Constraint,
    Group,
    Structure,
    _step,
    _with,
    motor_columns,
)
from models.mechanism_kin import _basis as kin_basis
from models.rigid import matrix_to_rotvec

Targets = Mapping[str, np.ndarray]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of rows, (n, 3) × (n, 3) or (3,) → (n, 3) (numpy's general ``cross`` costs more)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


_BASES: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`models.mechanism_kin._basis`, remembered per axis (the axes are the file's constants)."""
    key = np.asarray(n, dtype=float).tobytes()
    if key not in _BASES:
        _BASES[key] = kin_basis(n)
    return _BASES[key]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", a, b)


def _vm(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Row vectors times matrices: (n, 3) × (n, 3, k) → (n, k)."""
    return np.einsum("ni,nij->nj", v, M)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _skew(v: np.ndarray) -> np.ndarray:
    K = np.zeros((v.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return K


def _dlog(r: np.ndarray) -> np.ndarray:
    """The inverse left Jacobian of SO(3) at each rotation vector of ``r`` (n, 3) → (n, 3, 3)."""
    th = np.sqrt(_dot(r, r))
    K = _skew(r)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0, 1.0 / ts**2 - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)))
    return EYE3 - 0.5 * K + c[:, None, None] * (K @ K)


def _point_jac(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """d(R p + t)/d[δt, δw] for a point fixed to a body, (n, 3, 6)."""
    x = R @ p
    J = np.zeros((R.shape[0], 3, 6))
    J[:, [0, 1, 2], [0, 1, 2]] = 1.0
    J[:, 0, 4], J[:, 0, 5], J[:, 1, 3] = x[:, 2], -x[:, 1], -x[:, 2]
    J[:, 1, 5], J[:, 2, 3], J[:, 2, 4] = x[:, 0], x[:, 1], -x[:, 0]
    return J


def _T(R: np.ndarray) -> np.ndarray:
    return np.swapaxes(R, -1, -2)


# ---------------------------------------------------------------------------- constraints, vectorised
def _revolute(j: Joint, Ra, ta, Rb, tb, target):
    p, nrm = j.anchor, j.axis
    e1, e2 = _basis(nrm)
    n, m = Ra.shape[0], (6 if target is not None else 5)
    r, Ja, Jb = np.zeros((n, m)), np.zeros((n, m, 6)), np.zeros((n, m, 6))
    r[:, :3] = (Rb @ p + tb) - (Ra @ p + ta)
    Jb[:, :3], Ja[:, :3] = _point_jac(Rb, p), -_point_jac(Ra, p)
    bn, ae1, ae2 = Rb @ nrm, Ra @ e1, Ra @ e2
    for i, ae in ((3, ae1), (4, ae2)):
        r[:, i] = _dot(bn, ae)
        Jb[:, i, 3:] = _cross(bn, ae)
        Ja[:, i, 3:] = -Jb[:, i, 3:]
    if target is not None:
        be1 = Rb @ e1
        x, y = _dot(be1, ae1), _dot(be1, ae2)
        r[:, 5] = _wrap(np.arctan2(y, x) - target)
        h = (x * x + y * y)[:, None]
        x, y = x[:, None], y[:, None]
        Jb[:, 5, 3:] = (x * _cross(be1, ae2) - y * _cross(be1, ae1)) / h
        Ja[:, 5, 3:] = (x * _cross(ae2, be1) - y * _cross(ae1, be1)) / h
    return r, Ja, Jb


def _prismatic(j: Joint, Ra, ta, Rb, tb, target):
    c, d = j.anchor, j.axis
    e1, e2 = _basis(d)
    n, m = Ra.shape[0], (6 if target is not None else 5)
    r, Ja, Jb = np.zeros((n, m)), np.zeros((n, m, 6)), np.zeros((n, m, 6))
    delta = (Rb @ c + tb) - (Ra @ c + ta)
    Db, Da = _point_jac(Rb, c), -_point_jac(Ra, c)
    ad = Ra @ d
    s = _dot(ad, delta)
    Js_b, Js_a = _vm(ad, Db), _vm(ad, Da)
    Js_a[:, 3:] += _cross(ad, delta)
    for i, e in ((0, e1), (1, e2)):
        ae = Ra @ e
        r[:, i] = _dot(ae, delta)
        Jb[:, i], Ja[:, i] = _vm(ae, Db), _vm(ae, Da)
        Ja[:, i, 3:] += _cross(ae, delta)
    tilt = j.tilt_axis is not None
    E = Rb @ _T(Ra @ _exp(np.outer(s, j.tilt_axis * j.tilt_rate)) if tilt else Ra)
    r[:, 2:5] = matrix_to_rotvec(E)
    L = _dlog(r[:, 2:5])
    Jb[:, 2:5, 3:], Ja[:, 2:5, 3:] = L, -L @ E
    if tilt:
        k = (L @ (Rb @ j.tilt_axis)[:, :, None])[:, :, 0] * j.tilt_rate
        Jb[:, 2:5] -= k[:, :, None] * Js_b[:, None, :]
        Ja[:, 2:5] -= k[:, :, None] * Js_a[:, None, :]
    if target is not None:
        r[:, 5] = s - target
        Jb[:, 5], Ja[:, 5] = Js_b, Js_a
    return r, Ja, Jb


def _spherical(j: Joint, Ra, ta, Rb, tb, target):
    p = j.anchor
    return (Rb @ p + tb) - (Ra @ p + ta), -_point_jac(Ra, p), _point_jac(Rb, p)


def _fixed(j: Joint, Ra, ta, Rb, tb, target):
    n = Ra.shape[0]
    r, Ja, Jb = np.zeros((n, 6)), np.zeros((n, 6, 6)), np.zeros((n, 6, 6))
    r[:, :3], Ja[:, :3], Jb[:, :3] = _spherical(j, Ra, ta, Rb, tb, None)
    E = Rb @ _T(Ra)
    r[:, 3:] = matrix_to_rotvec(E)
    L = _dlog(r[:, 3:])
    Jb[:, 3:, 3:], Ja[:, 3:, 3:] = L, -L @ E
    return r, Ja, Jb


def _rod(c: Coupler, Ra, ta, Rb, tb, target):
    d = (Ra @ c.a_point + ta) - (Rb @ c.b_point + tb)
    L = np.sqrt(_dot(d, d))
    u = d / L[:, None]
    Ja, Jb = _vm(u, _point_jac(Ra, c.a_point))[:, None], -_vm(u, _point_jac(Rb, c.b_point))[:, None]
    return (L - c.length)[:, None], Ja, Jb


def _turn(R: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1, e2 = _basis(n)
    be1 = R @ e1
    x, y = be1 @ e1, be1 @ e2
    g = (x[:, None] * _cross(be1, e2) - y[:, None] * _cross(be1, e1)) / (x * x + y * y)[:, None]
    return np.arctan2(y, x), g


def _gear(c: Coupler, Ra, ta, Rb, tb, target):
    tha, ga = _turn(Ra, c.axis)
    thb, gb = _turn(Rb, c.axis)
    n = Ra.shape[0]
    Ja, Jb = np.zeros((n, 1, 6)), np.zeros((n, 1, 6))
    Ja[:, 0, 3:], Jb[:, 0, 3:] = -c.ratio * ga, gb
    return (thb - c.ratio * tha)[:, None], Ja, Jb


_EVAL = {"revolute": _revolute, "prismatic": _prismatic, "spherical": _spherical, "fixed": _fixed, "rod": _rod,
         "gear": _gear}


# ---------------------------------------------------------------------------- residuals and Newton
def _body(R: np.ndarray, t: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
    if i < 0:
        return np.broadcast_to(EYE3, (R.shape[0], 3, 3)), np.zeros((R.shape[0], 3))
    return R[:, i], t[:, i]


def group_residual(group: Group, R: np.ndarray, t: np.ndarray, targets: Targets,
                   jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """c(s) of one group at every pose (n, m) and its Jacobians (n, m, size), as
    :func:`models.mechanism_kin.group_residual` row by row; ``targets``: each motor's joint values (n,)."""
    n = R.shape[0]
    m = sum(c.rows() for c in group.constraints)
    r = np.zeros((n, m))
    J = np.zeros((n, m, group.size)) if jacobian else None
    col = {b: 6 * k for k, b in enumerate(group.bodies)}
    row = 0
    for c in group.constraints:
        Ra, ta = _body(R, t, c.a)
        Rb, tb = _body(R, t, c.b)
        rc, Ja, Jb = _EVAL[c.kind](c.item, Ra, ta, Rb, tb, None if c.motor is None else targets[c.motor])
        k = rc.shape[1]
        r[:, row:row + k] = rc
        if J is not None:
            if c.a >= 0:
                J[:, row:row + k, col[c.a]:col[c.a] + 6] += Ja
            if c.b >= 0:
                J[:, row:row + k, col[c.b]:col[c.b] + 6] += Jb
        row += k
    return r, J


def _exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (m, 3) → (m, 3, 3): :func:`models.rigid.rotvec_to_matrix`'s formula."""
    th = np.sqrt(_dot(w, w))
    small = th < 1e-8
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    K = _skew(w)
    return EYE3 + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _apply(group: Group, R: np.ndarray, t: np.ndarray, dx: np.ndarray) -> None:
    """``t ← t + δt``, ``R ← exp(δw) R`` for every body of the group at every pose."""
    n, k = dx.shape[0], len(group.bodies)
    if not n:
        return
    d = dx.reshape(n, k, 6)
    bodies = list(group.bodies)
    t[:, bodies] += d[:, :, :3]
    R[:, bodies] = _exp(d[:, :, 3:].reshape(-1, 3)).reshape(n, k, 3, 3) @ R[:, bodies]


def _steps(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Newton steps of stacked systems: one batched square solve; pose by pose where a system is not square or is
    singular (least squares there, as :func:`models.mechanism_kin._step`)."""
    if J.shape[1] == J.shape[2]:
        try:
            return np.linalg.solve(J, -r[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            pass
    return np.array([_step(J[i], r[i]) for i in range(J.shape[0])]).reshape(J.shape[0], J.shape[2])


def _take(targets: Targets, idx: np.ndarray) -> dict[str, np.ndarray]:
    return {m: v[idx] for m, v in targets.items()}


def newton(group: Group, R: np.ndarray, t: np.ndarray, targets: Targets, iterations: int = 30) -> np.ndarray:
    """Newton on one group at every pose, in place; True where c(s) = 0 (:func:`models.mechanism_kin.newton`)."""
    ok = np.zeros(R.shape[0], bool)
    live = np.arange(R.shape[0])
    for _ in range(iterations):
        if not live.size:
            return ok
        r, J = group_residual(group, R[live], t[live], _take(targets, live))
        conv = np.max(np.abs(r), axis=1) < RESIDUAL_TOL
        ok[live[conv]] = True
        live, r, J = live[~conv], r[~conv], J[~conv]
        dx = _steps(J, r)
        good = np.all(np.isfinite(dx), axis=1) & (np.max(np.abs(dx), axis=1, initial=0.0) <= 1.0)
        live, dx = live[good], dx[good]
        Rl, tl = R[live], t[live]
        _apply(group, Rl, tl, dx)
        R[live], t[live] = Rl, tl
    if live.size:
        r, _ = group_residual(group, R[live], t[live], _take(targets, live), jacobian=False)
        ok[live] = np.max(np.abs(r), axis=1) < RESIDUAL_TOL * 100
    return ok


def _predict(group: Group, R: np.ndarray, t: np.ndarray, here: Targets, goal: Targets) -> np.ndarray:
    """Euler predictor of the continuation at every pose (:func:`models.mechanism_kin._predict`); False where the
    tangent step is too long (that pose untouched)."""
    _, J = group_residual(group, R, t, here)
    dc = np.zeros(J.shape[:2])
    row = 0
    for c in group.constraints:
        row += c.rows()
        if c.motor is not None:
            dc[:, row - 1] = -(goal[c.motor] - here[c.motor])
    dx = _steps(J, dc)
    finite = np.all(np.isfinite(dx), axis=1)
    short = np.max(np.abs(np.where(finite[:, None], dx, 0.0)), axis=1, initial=0.0) < PREDICT_MAX
    good = np.flatnonzero(finite & short)
    Rg, tg = R[good], t[good]
    _apply(group, Rg, tg, dx[good])
    R[good], t[good] = Rg, tg
    return ~finite | short


def _local(group: Group) -> Group:
    """The group with its bodies numbered 0..k-1 (the ground stays -1), for arrays of the group's bodies only."""
    at = {b: k for k, b in enumerate(group.bodies)}
    at[-1] = -1
    cons = tuple(Constraint(c.name, c.kind, at[c.a], at[c.b], c.item, c.motor) for c in group.constraints)
    return Group(tuple(range(len(group.bodies))), cons, group.motors)


def _columns(values: Targets, motors: Sequence[str], n: int) -> np.ndarray:
    """The motors' values (each a scalar or (n,)) as columns (n, motors)."""
    return np.stack([np.broadcast_to(np.asarray(values[m], float), (n,)) for m in motors] or [np.zeros(n)],
                    axis=1)[:, :len(motors)]


def solve_group(st: Structure, group: Group, R: np.ndarray, t: np.ndarray, start: Targets,
                goal: Targets) -> np.ndarray:
    """Move ``group`` at every pose from its solution at joint values ``start`` to ``goal`` (each (n,)) by
    continuation, in place, as :func:`models.mechanism_kin.solve_group` pose by pose; returns the poses where it
    failed (an assembly error there; their state is left part way)."""
    spec, n = st.spec, R.shape[0]
    local, bodies = _local(group), list(group.bodies)
    Rg, tg = R[:, bodies], t[:, bodies]
    motors = group.motors
    s0, g0 = _columns(start, motors, n), _columns(goal, motors, n)
    unit = np.array([STEP[spec.joints[spec.motors[m].joint].kind] for m in motors])
    span = np.max(np.abs(g0 - s0) / unit, axis=1, initial=0.0)
    done, frac = np.zeros(n), 1.0 / np.maximum(1.0, np.ceil(span))
    depth, failed = np.zeros(n, int), np.zeros(n, bool)
    while True:
        live = np.flatnonzero((done < 1.0 - 1e-12) & ~failed)
        if not live.size:
            break
        nxt = np.minimum(1.0, done[live] + frac[live])
        a, b = s0[live], g0[live]
        here = a + done[live][:, None] * (b - a)
        to = a + nxt[:, None] * (b - a)
        Rt, tt = Rg[live], tg[live]
        here_t = {m: here[:, k] for k, m in enumerate(motors)}
        to_t = {m: to[:, k] for k, m in enumerate(motors)}
        ok = _predict(local, Rt, tt, here_t, to_t)
        pi = np.flatnonzero(ok)
        Rp, tp = Rt[pi], tt[pi]
        ok[pi] = newton(local, Rp, tp, _take(to_t, pi))
        Rt[pi], tt[pi] = Rp, tp
        acc, rej = live[ok], live[~ok]
        Rg[acc], tg[acc], done[acc] = Rt[ok], tt[ok], nxt[ok]
        depth[rej] += 1
        frac[rej] /= 2
        failed[rej[depth[rej] > 8]] = True
    R[:, bodies], t[:, bodies] = Rg, tg
    return failed


# ---------------------------------------------------------------------------- derivatives
def state_derivatives(st: Structure, group: Group, R: np.ndarray, t: np.ndarray, targets: Targets,
                      params: Sequence[str] = (), h: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Implicit derivatives of the group's coordinates at every pose's solution, as
    :func:`models.mechanism_kin.state_derivatives`: shapes (n, size, motors) and (n, size, params)."""
    r, J = group_residual(group, R, t, targets)
    assert J is not None
    pinv = np.linalg.pinv(J)
    dc_dq = motor_columns(group, r.shape[1])
    dc_dp = np.zeros((r.shape[0], r.shape[1], len(params)))
    for k, p in enumerate(params):
        if p.startswith("motors."):
            raise KeyError(f"{p}: a motor ratio scales the joint value, not c(s); differentiate the motor value")
        v = get_param(st.spec, p)
        rp = group_residual(_with(st, group, {p: v + h}), R, t, targets, jacobian=False)[0]
        rm = group_residual(_with(st, group, {p: v - h}), R, t, targets, jacobian=False)[0]
        dc_dp[:, :, k] = (rp - rm) / (2 * h)
    return -pinv @ dc_dq, -pinv @ dc_dp


def body_jacobian(st: Structure, R: np.ndarray, body: str, dx: np.ndarray, group: Group) -> np.ndarray:
    """d[frame origin position; rotation] of ``body`` at every pose from group-coordinate derivatives ``dx``
    (n, size, k) → (n, 6, k), as :func:`models.mechanism_kin.body_jacobian`."""
    i = st.index(body)
    if i < 0 or i not in group.bodies:
        return np.zeros((dx.shape[0], 6, dx.shape[2]))
    k = group.bodies.index(i)
    block = dx[:, 6 * k:6 * k + 6]
    origin = st.spec.bodies[body].origin
    return np.concatenate([_point_jac(R[:, i], origin) @ block, block[:, 3:]], axis=1)
