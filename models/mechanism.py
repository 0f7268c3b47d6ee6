"""A head's mechanism as data: motor values → 6-DoF poses of every body, with each motor's zero error and hard stops.

The mechanism is a file (:mod:`models.mechanism_file`, named by the head config's ``[paths] mechanism``): rigid
bodies, joints, couplers and motors. :class:`Mechanism` solves its closure constraints c(s) = 0
(:mod:`models.mechanism_kin`) for the motor values, continuing from its previous solution so every linkage stays on
its assembly branch, and gives each attachment link's pose and its derivatives with respect to the motor values and
to design parameters. ``zero_error`` and ``stops`` model a physical head: the joint a motor drives sees
``clip(value − zero_error, stop_lo, stop_hi)``. The emulated "real" sample head with such perturbations is
:func:`sim_hardware.mechanism.sample_mechanism`.

Frame: the skin mesh's frame in metres, x to the head's left, y up, z forward.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models import mechanism_batch
from models.errors import SpecError
from models.mechanism_file import Body, MechanismSpec, read_mechanism, spec_from_dict
from models.mechanism_kin import (
    RESIDUAL_TOL,
    AssemblyError,
    State,
    body_jacobian,
    free_bodies,
    group_residual,
    joint_targets,
    solve_group,
    state_derivatives,
    structure,
)

__all__ = ["SAMPLE_MECHANISM", "AssemblyError", "Mechanism", "load_mechanism", "mechanism_from_dict"]

#: The sample head's mechanism file.
SAMPLE_MECHANISM = Path(__file__).resolve().parents[1] / "heads" / "sample" / "mechanism.toml"


def check_constrained(spec: MechanismSpec) -> MechanismSpec:
    """Refuse (SpecError) a mechanism with a body still free when every motor is held (too few constraints)."""
    free = free_bodies(spec)
    if free:
        bodies, dof = free
        raise SpecError(spec.source, f"bodies.{bodies[0]}", f"a loop with too few constraints: with every motor "
                        f"held, {', '.join(bodies)} can still move ({dof} degree(s) of freedom left); add a joint, "
                        "a rod or a gear, or a motor on an actuated joint")
    return spec


def load_mechanism(path: str | Path) -> MechanismSpec:
    """Read a mechanism file and check it completely; SpecError naming the file, key and why."""
    return check_constrained(read_mechanism(path))


def mechanism_from_dict(data: Mapping[str, Any], source: str = "<mechanism>") -> MechanismSpec:
    """Check a parsed mechanism file completely (see :func:`load_mechanism`)."""
    return check_constrained(spec_from_dict(data, source))


class Mechanism:
    """A solved mechanism: ``link_poses(actuators)`` maps SI motor values to each attachment link's 4x4 pose.

    Not thread-safe across concurrent solves by design of its cache; one lock serialises them.
    """

    def __init__(self, spec: MechanismSpec, zero_error: Mapping[str, float] | None = None,
                 stops: Mapping[str, tuple[float, float]] | None = None) -> None:
        self.spec = spec
        self.structure = structure(spec)
        self.zero_error: dict[str, float] = dict(zero_error or {})
        self.stops: dict[str, tuple[float, float]] = dict(stops or {})
        self._state = State.neutral(len(self.structure.bodies))
        self._targets = joint_targets(spec, {})
        self._lock = threading.Lock()
        # assemble at motor zero: a spec whose parameters moved (a fit, a design) no longer closes at s = 0
        for g in self.structure.groups:
            r, _ = group_residual(g, self._state, self._targets, jacobian=False)
            if np.max(np.abs(r), initial=0.0) >= RESIDUAL_TOL:  # (a closed group would take a zero step)
                solve_group(self.structure, g, self._state, self._targets, self._targets)

    @classmethod
    def load(cls, path: str | Path) -> Mechanism:
        """The mechanism of a file, at its design values (no zero error, no stops)."""
        return cls(load_mechanism(path))

    @property
    def actuators(self) -> tuple[str, ...]:
        return self.spec.motor_names

    @property
    def links(self) -> dict[str, Body]:
        """The attachment links: bodies carrying a skin node set."""
        return {n: self.spec.bodies[n] for n in self.spec.links}

    def joint_angles(self, actuators: Mapping[str, float]) -> dict[str, float]:
        """What each motor's joint sees: the value minus the zero error, clipped at the hard stops (SI)."""
        out = {}
        for name in self.actuators:
            value = float(actuators.get(name, 0.0)) - self.zero_error.get(name, 0.0)
            lo, hi = self.stops.get(name, (-math.inf, math.inf))
            out[name] = min(max(value, lo), hi)
        return out

    def solve(self, actuators: Mapping[str, float]) -> State:
        """Solve c(s) = 0 at these actuator values from the previous solution; AssemblyError when it cannot."""
        goal = joint_targets(self.spec, self.joint_angles(actuators))
        with self._lock:
            for g in self.structure.groups:
                if any(goal[m] != self._targets[m] for m in g.motors):
                    try:
                        solve_group(self.structure, g, self._state, self._targets, goal)
                    except AssemblyError:
                        # back to neutral, then try once more from there (another branch may have been lost)
                        for b in g.bodies:
                            self._state.R[b], self._state.t[b] = np.eye(3), 0.0
                        neutral = joint_targets(self.spec, {})
                        solve_group(self.structure, g, self._state, neutral, goal)
                    for m in g.motors:
                        self._targets[m] = goal[m]
            return self._state.copy()

    def joint_targets_many(self, actuators: Sequence[str], P: np.ndarray) -> dict[str, np.ndarray]:
        """Each motor's joint value (n,) at the rows of ``P`` (n, len(actuators)), SI: :meth:`joint_angles` times
        the motor's ratio, row by row (motors not in ``actuators``: value zero)."""
        P = np.asarray(P, dtype=float).reshape(-1, len(actuators))
        col = {a: k for k, a in enumerate(actuators)}
        out = {}
        for name in self.actuators:
            value = (P[:, col[name]] if name in col else np.zeros(len(P))) - self.zero_error.get(name, 0.0)
            lo, hi = self.stops.get(name, (-math.inf, math.inf))
            out[name] = self.spec.motors[name].ratio * np.minimum(np.maximum(value, lo), hi)
        return out

    def solve_many(self, actuators: Sequence[str], P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Solve c(s) = 0 at every row of ``P`` (n, len(actuators)), SI, each from the solution this mechanism holds
        (left unchanged): each row's state as :meth:`solve` would reach from there (a pose that cannot be reached
        from there is solved again from neutral; AssemblyError when neither works). Vectorised over the rows: for
        calibration and tabulation. Returns each body's ``R`` (n, bodies, 3, 3) and ``t`` (n, bodies, 3)."""
        goal = self.joint_targets_many(actuators, P)
        n = len(next(iter(goal.values()))) if goal else len(np.atleast_2d(P))
        with self._lock:
            R = np.repeat(self._state.R[None], n, axis=0)
            t = np.repeat(self._state.t[None], n, axis=0)
            held = dict(self._targets)
        neutral = joint_targets(self.spec, {})
        for g in self.structure.groups:
            idx = np.flatnonzero(np.any([goal[m] != held[m] for m in g.motors], axis=0)) if g.motors else []
            if not len(idx):
                continue
            Rs, ts = R[idx], t[idx]
            failed = mechanism_batch.solve_group(self.structure, g, Rs, ts, held, {m: goal[m][idx] for m in g.motors})
            for i in np.flatnonzero(failed):  # back to neutral and once more from there, as solve does
                state = State.neutral(len(self.structure.bodies))
                solve_group(self.structure, g, state, neutral, {m: float(goal[m][idx[i]]) for m in g.motors})
                Rs[i][list(g.bodies)], ts[i][list(g.bodies)] = state.R[list(g.bodies)], state.t[list(g.bodies)]
            R[idx], t[idx] = Rs, ts
        return R, t

    def link_poses_many(self, actuators: Sequence[str], P: np.ndarray) -> dict[str, np.ndarray]:
        """Each link's tracked frame (n, 4, 4) at every row of ``P`` (see :meth:`solve_many`)."""
        R, t = self.solve_many(actuators, P)
        out = {}
        for name in self.spec.links:
            i, rest = self.structure.index(name), self.spec.bodies[name].rest
            T = np.zeros((len(R), 4, 4))
            T[:, 3, 3] = 1.0
            if i < 0:
                T[:, :3] = rest[:3]
            else:
                T[:, :3, :3] = R[:, i] @ rest[:3, :3]
                T[:, :3, 3] = R[:, i] @ rest[:3, 3] + t[:, i]
            out[name] = T
        return out

    def body_transforms(self, actuators: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Every body's rigid transform from neutral (4x4, head frame), the ground's the identity."""
        state = self.solve(actuators)
        return {n: state.transform(self.structure.index(n)) for n in self.spec.bodies}

    def transforms(self, actuators: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Each link's rigid transform from its neutral pose (4x4, head frame)."""
        state = self.solve(actuators)
        return {n: state.transform(self.structure.index(n)) for n in self.spec.links}

    def link_poses(self, actuators: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Each link's tracked frame (4x4, head frame, SI) at these actuator values."""
        return {n: T @ self.spec.bodies[n].rest for n, T in self.transforms(actuators).items()}

    def rest_poses(self) -> dict[str, np.ndarray]:
        """Each link's frame with every joint at its mechanical zero (the neutral configuration of the file)."""
        return {n: self.spec.bodies[n].rest.copy() for n in self.spec.links}

    def jacobian(self, actuators: Mapping[str, float], params: Sequence[str] = ()
                 ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Implicit derivatives of each link's [frame position (m); rotation increment δw (rad, head frame:
        R' = exp(δw) R)] at these values: with respect to the actuator values (6, A) (zero for a motor held at a
        hard stop) and to design parameters (6, P; names as :func:`models.mechanism_file.get_param`)."""
        state = self.solve(actuators)
        seen = self.joint_angles(actuators)
        goal = joint_targets(self.spec, seen)
        A = self.actuators
        d_act = {n: np.zeros((6, len(A))) for n in self.spec.links}
        d_par = {n: np.zeros((6, len(params))) for n in self.spec.links}
        for g in self.structure.groups:
            names = [n for n in self.spec.links if self.structure.index(n) in g.bodies]
            if not names:
                continue
            dq, dp = state_derivatives(self.structure, g, state, goal, params)
            for k, m in enumerate(g.motors):
                lo, hi = self.stops.get(m, (-math.inf, math.inf))
                moving = lo < float(actuators.get(m, 0.0)) - self.zero_error.get(m, 0.0) < hi
                dq[:, k] *= self.spec.motors[m].ratio if moving else 0.0
            for n in names:
                Jq = body_jacobian(self.structure, state, n, dq, g)
                for k, m in enumerate(g.motors):
                    d_act[n][:, A.index(m)] = Jq[:, k]
                d_par[n] += body_jacobian(self.structure, state, n, dp, g)
        return d_act, d_par

    def check_against(self, head: Any) -> None:
        """Refuse (SpecError) a mechanism whose motors or links differ from ``head`` (a HeadSpec), by name."""
        for what, mine, theirs in (("motors", set(self.actuators), set(head.actuator_names)),
                                   ("bodies", set(self.spec.links), {link.name for link in head.links})):
            if mine != theirs:
                raise SpecError(self.spec.source, what, f"head {head.name!r} differs: only in the head "
                                f"{sorted(theirs - mine)}, only in the mechanism {sorted(mine - theirs)}")
