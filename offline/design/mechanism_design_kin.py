"""A redesigned mechanism driving the skin: attachment motion c(p, θ) and its derivatives with respect to the
design variables θ, from the mechanism's implicit derivatives.

Convention: a design θ changes the linkages, so at motor zero the links may no longer sit at their old neutral
poses. The skin is mounted at the new mechanism's neutral configuration: each attachment plate is a rigid part of
its link's output body *as assembled at motor zero*, so the node sets move by T(p, θ) · T(0, θ)⁻¹ and the skin is at
rest at the neutral pose whatever the design. The mechanism file written for a design
(:mod:`offline.design.mechanism_design_head`) re-expresses every body at that configuration, so it says the same.

For a node X of a link's set (frame offset o as :class:`offline.dataset.fem_problem.FemSkin` applies it), with
the link frame G(p) = (Q(p), g(p)) and M = Q(p) Q(0)ᵀ, v = X + o − g(0), u = M v:

    x = M v + g(p) − o,   dx = dg(p) − [u]× δw(p) − M dg(0) + M [v]× δw(0)

where dg and δw (the rotation increment, R' = exp(δw) R) come from :func:`design_jacobian`: per group of the
mechanism, ``models.mechanism_kin.state_derivatives`` (implicit differentiation of c(s) = 0) for the design
parameters that group's constraints use; a motor ratio's column is the motor's own column times its value / ratio.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from models.mechanism import Mechanism
from models.mechanism_file import MechanismSpec
from models.mechanism_kin import body_jacobian, joint_targets, state_derivatives

from .mechanism_design_envelope import DesignSpace, tilted_axis

JOINT_KINDS = ("revolute", "prismatic", "spherical", "fixed")


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def design_jacobian(mech: Mechanism, values: Mapping[str, float], params: Sequence[str]
                    ) -> dict[str, np.ndarray]:
    """Each link's d[frame origin; δw] / d ``params`` (6, P) at motor ``values`` (SI), by implicit differentiation,
    each group differentiated only for the parameters its constraints use (motor ratios excluded: see
    :meth:`DesignedMechanism.link_derivatives`)."""
    st = mech.structure
    state = mech.solve(values)
    goal = joint_targets(mech.spec, mech.joint_angles(values))
    out = {n: np.zeros((6, len(params))) for n in mech.spec.links}
    for g in st.groups:
        names = [n for n in mech.spec.links if st.index(n) in g.bodies]
        if not names:
            continue
        used = {(("joints" if c.kind in JOINT_KINDS else "couplers"), c.name) for c in g.constraints}
        cols = [k for k, p in enumerate(params) if tuple(p.split(".")[:2]) in used]
        if not cols:
            continue
        _, dp = state_derivatives(st, g, state, goal, [params[k] for k in cols])
        for n in names:
            out[n][:, cols] = body_jacobian(st, state, n, dp, g)
    return out


class DesignedMechanism:
    """The mechanism at design θ: link transforms from the new neutral, and their derivatives in θ."""

    def __init__(self, space: DesignSpace, theta: np.ndarray) -> None:
        self.space = space
        self.theta = np.asarray(theta, dtype=np.float64).copy()
        self.spec: MechanismSpec = space.apply(self.theta)
        self.mech = Mechanism(self.spec)
        self.zero = {m: 0.0 for m in self.spec.motors}
        self.T0 = self.mech.body_transforms(self.zero)
        self._params, self._chain = self._parameter_chain()
        self._d0: dict[str, np.ndarray] | None = None

    def _parameter_chain(self) -> tuple[list[str], np.ndarray]:
        """The mechanism parameters the design variables touch and d(parameter)/dθ (P, D) (motor ratios aside)."""
        params: list[str] = []
        rows: list[tuple[int, int, float]] = []
        for g in self.space.groups:
            if g.item.startswith("motors."):
                continue
            if g.what == "axis":
                n0 = self.space.spec.joints[g.item.split(".", 1)[1]].axis
                w = self.theta[list(g.index)]
                h = 1e-7
                for k, col in enumerate(g.index):
                    e = np.zeros(2)
                    e[k] = h
                    d = (tilted_axis(n0, w + e) - tilted_axis(n0, w - e)) / (2 * h)
                    for i in range(3):
                        rows.append((len(params) + i, col, float(d[i])))
                params.extend(f"{g.item}.axis[{i}]" for i in range(3))
            elif g.kind == "ball":
                for i, col in enumerate(g.index):
                    rows.append((len(params), col, 1.0))
                    params.append(f"{g.item}.{g.what}[{i}]")
            else:
                rows.append((len(params), g.index[0], 1.0))
                params.append(f"{g.item}.{g.what}")
        chain = np.zeros((len(params), self.space.size))
        for r, c, v in rows:
            chain[r, c] += v
        return params, chain

    def check_range(self, lo: Mapping[str, float], hi: Mapping[str, float], n: int = 7) -> None:
        """Raise AssemblyError unless every linkage assembles over its motors' whole range (``n`` values per motor,
        a grid for linkages with several motors, each point reached by continuation from the held solution, all
        points at once: :meth:`models.mechanism.Mechanism.solve_many`)."""
        import itertools

        names = list(self.zero)
        for g in self.mech.structure.groups:
            if not g.motors:
                continue
            k = n if len(g.motors) == 1 else max(3, n // 2 + 1)
            axes = [np.linspace(lo[m], hi[m], k) for m in g.motors]
            grid = np.array([[{**self.zero, **dict(zip(g.motors, point, strict=True))}[a] for a in names]
                             for point in itertools.product(*axes)])
            self.mech.solve_many(names, grid)

    def transforms(self, values: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Each link's rigid motion from the new neutral: T(p, θ) · T(0, θ)⁻¹ (4x4)."""
        T = self.mech.body_transforms(values)
        return {n: T[n] @ np.linalg.inv(self.T0[n]) for n in self.spec.links}

    def _frame_derivatives(self, values: Mapping[str, float]) -> dict[str, np.ndarray]:
        """d[frame origin; δw]/dθ (6, D) of each link at ``values``."""
        dpar = design_jacobian(self.mech, values, self._params)
        out = {n: d @ self._chain for n, d in dpar.items()}
        motor_groups = [g for g in self.space.groups if g.item.startswith("motors.")]
        if motor_groups:
            d_act, _ = self.mech.jacobian(values)
            names = self.mech.actuators
            for g in motor_groups:
                m = g.item.split(".", 1)[1]
                k = names.index(m)
                scale = float(values.get(m, 0.0)) / self.spec.motors[m].ratio
                for n in out:
                    out[n][:, g.index[0]] += d_act[n][:, k] * scale
        return out

    def link_derivatives(self, values: Mapping[str, float]) -> dict[str, tuple[np.ndarray, np.ndarray,
                                                                                 np.ndarray, np.ndarray]]:
        """Per link (M, g(0), d_p, d_0): the relative rotation Q(p)Q(0)ᵀ, the neutral frame origin, and the frame
        derivatives (6, D) at ``values`` and at motor zero."""
        if self._d0 is None:
            self._d0 = self._frame_derivatives(self.zero)
        dp = self._frame_derivatives(values)
        T = self.mech.body_transforms(values)
        out = {}
        for n in self.spec.links:
            o = self.spec.bodies[n].origin
            M = T[n][:3, :3] @ self.T0[n][:3, :3].T
            g0 = self.T0[n][:3, :3] @ o + self.T0[n][:3, 3]
            out[n] = (M, g0, dp[n], self._d0[n])
        return out


def points_derivative(M: np.ndarray, g0: np.ndarray, d_p: np.ndarray, d_0: np.ndarray, X: np.ndarray
                      ) -> np.ndarray:
    """d x / dθ (n, 3, D) of points X (n, 3; already shifted by the frame offset) moved by T(p)T(0)⁻¹."""
    v = X - g0
    u = v @ M.T
    dg_p, dw_p, dg_0, dw_0 = d_p[:3], d_p[3:], d_0[:3], d_0[3:]
    out = np.empty((len(X), 3, d_p.shape[1]))
    base = dg_p - M @ dg_0
    for i in range(len(X)):
        out[i] = base - _skew(u[i]) @ dw_p + M @ _skew(v[i]) @ dw_0
    return out
