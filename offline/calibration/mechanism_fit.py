"""Calibration of the mechanism itself: zero offsets, rod lengths and joint positions fitted to tracked link poses.

The alternative to the free polynomial link map: the head's mechanism file (``[paths] mechanism``) with its parameters
adjusted by robust Gauss-Newton (scipy's ``least_squares``) so the solved link frames match the tracked ones. Each
independent group of bodies (a linkage and what it carries) is fitted on its own: its motors' zero offsets, its rods'
lengths and the anchors of the joints that hold its links, each with a weak prior at its design value so directions
the data cannot see stay put. The Jacobian comes from the mechanism's implicit derivatives. The runtime still needs a
fast map: :func:`linkmap_from_mechanism` tabulates the fitted mechanism as a cubic link map.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from models import mechanism_batch
from models.linkmap import FitOptions, LinkMap, LinkObservations, fit_linkmap
from models.mechanism import Mechanism
from models.mechanism_file import MechanismSpec, get_param, with_params
from models.mechanism_kin import Group
from models.rigid import matrix_to_quat, matrix_to_rotvec

#: Lever (m) that turns a rotation error into a length, so positions and orientations weigh alike.
LEVER_M = 0.03
#: Prior standard deviations at the design values: joint anchors and rod lengths (m), zero offsets (rad).
PRIOR_ANCHOR_M = 2e-3
PRIOR_LENGTH_M = 1e-3
PRIOR_ZERO_RAD = math.radians(5.0)
#: Unit of the residuals (m): about a tracked pose's noise, so the priors above stay weak against the data.
LOSS_SCALE_M = 0.1e-3
#: Robust loss: residuals beyond this many units count linearly (marker swaps that survived the capture's rejection).
ROBUST_UNITS = 3.0


@dataclass
class MechanismFit:
    """A fitted mechanism: its zero offsets and parameters, and the fit's residual (mm) on its own samples."""

    mechanism: Mechanism
    zero_offsets: dict[str, float]
    params: dict[str, tuple[float, float]]  # name -> (design, fitted)
    residual_rms_mm: float
    groups: int = 0
    evaluations: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """Fitted values for the report (mm and degrees)."""
        return {
            "zero_offsets_deg": {n: math.degrees(v) for n, v in self.zero_offsets.items()},
            "params": {n: {"design": d, "fitted": f, "moved_mm": (f - d) * 1e3} for n, (d, f) in self.params.items()},
            "fit_rms_mm": self.residual_rms_mm,
            "evaluations": self.evaluations,
        }


def fit_parameters(spec: MechanismSpec, group: Group, bodies: Sequence[str], anchors: bool = True) -> list[str]:
    """The design parameters calibration adjusts in one group: rod lengths and (``anchors``) the anchors of joints
    whose child is one of the group's bodies (hinges, guides, pins), every coordinate."""
    names = set(bodies)
    cons = {c.name for c in group.constraints}
    out = [f"couplers.{c.name}.length" for c in spec.couplers.values() if c.kind == "rod" and c.name in cons]
    for j in spec.joints.values() if anchors else ():
        if j.name in cons and j.child in names and j.kind != "fixed":
            out.extend(f"joints.{j.name}.anchor[{i}]" for i in range(3))
    return out


def fit_mechanism(spec: MechanismSpec, actuators: Sequence[str], P: np.ndarray,
                  observations: Mapping[str, LinkObservations], max_evaluations: int = 12,
                  anchors: bool = True) -> MechanismFit:
    """Fit zero offsets and parameters of ``spec`` to samples ``P`` (n, A) (SI, ``actuators`` order) and the tracked
    frames of its links; groups are fitted one after the other. ``anchors``: joint positions too (slower), else
    zero offsets and rod lengths."""
    base = Mechanism(spec)
    zeros: dict[str, float] = {m: 0.0 for m in spec.motors}
    values: dict[str, float] = {}
    sq: list[np.ndarray] = []
    evals = 0
    for g in base.structure.groups:
        bodies = [base.structure.bodies[b] for b in g.bodies]
        links = [n for n in spec.links if n in bodies and n in observations]
        if not g.motors or not any(observations[n].valid.any() for n in links):
            continue
        params = fit_parameters(spec, g, bodies, anchors)
        x0 = np.r_[np.zeros(len(g.motors)), [get_param(spec, p) for p in params]]
        prior = np.r_[np.full(len(g.motors), PRIOR_ZERO_RAD),
                      [PRIOR_LENGTH_M if p.endswith(".length") else PRIOR_ANCHOR_M for p in params]]
        cols = [list(actuators).index(m) for m in g.motors]
        problem = _GroupProblem(spec, g, links, params, P[:, cols], observations, x0, prior)
        sol = least_squares(problem.residual, x0, jac=problem.jacobian, loss="soft_l1",
                            f_scale=ROBUST_UNITS, max_nfev=max_evaluations, x_scale=prior)
        evals += problem.evaluations
        for k, m in enumerate(g.motors):
            zeros[m] = float(sol.x[k])
        values.update({p: float(v) for p, v in zip(params, sol.x[len(g.motors):], strict=True)})
        r = problem.residual(sol.x)[: -len(x0)] * LOSS_SCALE_M
        sq.append(r.reshape(-1, 3)[::2])  # position rows only, metres
    fitted = Mechanism(with_params(spec, values), zero_error=zeros)
    pos = np.concatenate(sq) if sq else np.zeros((0, 3))
    rms = float(np.sqrt(np.mean(np.sum(pos**2, axis=1))) * 1e3) if pos.size else float("nan")
    return MechanismFit(fitted, zeros, {p: (get_param(spec, p), v) for p, v in values.items()}, rms,
                        groups=len(sq), evaluations=evals)


class _GroupProblem:
    """Residuals (in units of LOSS_SCALE_M) and their Jacobian for one group, computed together and cached."""

    def __init__(self, spec: MechanismSpec, group: Group, links: list[str], params: list[str], Q: np.ndarray,
                 observations: Mapping[str, LinkObservations], x0: np.ndarray, prior: np.ndarray) -> None:
        self.spec, self.group, self.links, self.params, self.Q = spec, group, links, params, Q
        self.obs = {n: observations[n] for n in links}
        self.observed = {n: (o.positions, o.rotations()) for n, o in self.obs.items()}
        self.x0, self.prior = x0, prior
        self.evaluations = 0
        self._key: bytes | None = None
        self._warm: tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]] | None = None
        self._out: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros((0, 0)))

    def _eval(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._key == x.tobytes():
            return self._out
        self.evaluations += 1
        g, nm = self.group, len(self.group.motors)
        zeros = dict(zip(g.motors, x[:nm], strict=True))
        mech = Mechanism(with_params(self.spec, dict(zip(self.params, x[nm:], strict=True))), zero_error=zeros)
        st = mech.structure
        ratio = np.array([self.spec.motors[m].ratio for m in g.motors])
        goal = mech.joint_targets_many(g.motors, self.Q)
        R, t = self._solve(mech, goal)
        dq, dp = mechanism_batch.state_derivatives(st, g, R, t, goal, self.params)
        dz = -dq * ratio  # the joint sees ratio × (value − zero)
        res = np.zeros((len(self.Q), len(self.links), 6))
        jac = np.zeros((len(self.Q), len(self.links), 6, len(x)))
        for k, n in enumerate(self.links):
            i, rest = st.index(n), self.spec.bodies[n].rest
            p_obs, R_obs = self.observed[n]
            rot = R[:, i] @ rest[:3, :3]
            res[:, k, :3] = R[:, i] @ rest[:3, 3] + t[:, i] - p_obs
            res[:, k, 3:] = matrix_to_rotvec(rot @ np.swapaxes(R_obs, 1, 2)) * LEVER_M
            jac[:, k, :, :nm] = mechanism_batch.body_jacobian(st, R, n, dz, g)
            jac[:, k, :, nm:] = mechanism_batch.body_jacobian(st, R, n, dp, g)
        jac[:, :, 3:] *= LEVER_M
        valid = np.stack([self.obs[n].valid for n in self.links], axis=1)  # sample-major rows, as tracked
        r = res[valid].reshape(-1) / LOSS_SCALE_M
        J = jac[valid].reshape(-1, len(x)) / LOSS_SCALE_M
        # weak priors at the design values, in the same units as a tracked millimetre
        r = np.r_[r, (x - self.x0) / self.prior]
        J = np.vstack([J, np.diag(1.0 / self.prior)])
        self._key, self._out = x.tobytes(), (r, J)
        return r, J

    def _solve(self, mech: Mechanism, goal: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Every sample's solution at once: continued from the previous evaluation's solutions (parameters a
        little apart, so Newton needs few steps; the same branch), else from the assembly at motor zero."""
        g = next(h for h in mech.structure.groups if h.bodies == self.group.bodies)  # with these parameters
        target = {m: goal[m] for m in g.motors}
        if self._warm is None:
            R, t = mech.solve_many(g.motors, self.Q)
        else:
            R, t, start = self._warm[0].copy(), self._warm[1].copy(), self._warm[2]
            failed = mechanism_batch.solve_group(mech.structure, g, R, t, start, target)
            if failed.any():
                R[failed], t[failed] = mech.solve_many(g.motors, self.Q[failed])
        self._warm = (R, t, target)
        return R, t

    def residual(self, x: np.ndarray) -> np.ndarray:
        return self._eval(x)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return self._eval(x)[1]


def holdout_errors_mm(mech: Mechanism, actuators: Sequence[str], P: np.ndarray,
                      observations: Mapping[str, LinkObservations]) -> dict[str, np.ndarray]:
    """Per link, the 3-D position error (mm) of the mechanism's frames against observed ones at samples ``P``."""
    poses = mech.link_poses_many(actuators, P)
    return {n: np.linalg.norm(poses[n][o.valid, :3, 3] - o.positions[o.valid], axis=1) * 1e3
            for n, o in observations.items() if n in mech.links}


def linkmap_from_mechanism(mech: Mechanism, head: Any, samples: int = 300, seed: int = 0, degree: int = 3,
                           provenance: Mapping[str, Any] | None = None) -> LinkMap:
    """The runtime's fast map of a mechanism: a degree-``degree`` polynomial per link fitted to noise-free poses
    at ``samples`` random actuator vectors within the head's limits (each link on the head config's actuators)."""
    rng = np.random.default_rng(seed)
    names = list(head.actuator_names)
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    P = rng.uniform(lo, hi, (samples, len(names)))
    P[0] = np.array(head.neutral_pose)  # the neutral pose itself, exactly
    poses = mech.link_poses_many(names, P)
    obs = {n: LinkObservations(T[:, :3, 3], matrix_to_quat(T[:, :3, :3]), np.ones(len(P), bool))
           for n, T in poses.items()}
    config_links = {link.name: link.actuators for link in head.links}
    # noise-free samples: detection would keep only what moves; the config's actuators are the mechanism's
    opts = FitOptions(min_detection_dof=10**9)
    return fit_linkmap(names, head.neutral_pose, (hi - lo) / 2, P, obs, config_links=config_links,
                       rigid=[link.name for link in head.links if link.rigid], head=head.name,
                       provenance=provenance, options=opts, degree=degree,
                       units={a.name: (a.unit, a.unit_scale) for a in head.actuators})


def _subset(obs: Mapping[str, LinkObservations], mask: np.ndarray) -> dict[str, LinkObservations]:
    return {n: LinkObservations(o.positions[mask], o.quaternions[mask], o.valid[mask]) for n, o in obs.items()}


def _rms(errors: Mapping[str, np.ndarray]) -> float | None:
    e = np.concatenate([np.asarray(v) for v in errors.values()]) if errors else np.zeros(0)
    return float(np.sqrt(np.mean(e**2))) if e.size else None


def choose_link_map(head: Any, quadratic: LinkMap, P: np.ndarray, obs: Mapping[str, LinkObservations],
                    fit_mask: np.ndarray, holdout: np.ndarray, mode: str = "auto", fit_joints: bool = False
                    ) -> tuple[LinkMap, dict[str, Any]]:
    """Fit the head's mechanism on the fit samples, compare its hold-out error with the quadratic map's on the same
    hold-out samples, and return the map the runtime should use with the comparison for the report.

    ``mode``: ``auto`` (the smaller hold-out RMS; the quadratic map without hold-out poses), ``mechanism`` (the
    mechanism whatever the errors). The mechanism's runtime map is its cubic tabulation
    (:func:`linkmap_from_mechanism`)."""
    from models.mechanism import load_mechanism

    names = list(head.actuator_names)
    spec = load_mechanism(head.path("mechanism"))
    fit = fit_mechanism(spec, names, P[fit_mask], _subset(obs, fit_mask), anchors=fit_joints)
    section: dict[str, Any] = {"mechanism_fit": fit.to_json(), "mode": mode}
    if holdout.any():
        hold = _subset(obs, holdout)
        pred = quadratic.predict(P[holdout])
        q_err = {n: np.linalg.norm(pred[n][o.valid, :3] - o.positions[o.valid], axis=1) * 1e3
                 for n, o in hold.items() if n in pred}
        m_err = holdout_errors_mm(fit.mechanism, names, P[holdout], hold)
        section["holdout_rms_mm"] = {"quadratic": _rms(q_err), "mechanism": _rms(m_err)}
    rms = section.get("holdout_rms_mm", {})
    use_mech = mode == "mechanism" or (rms and rms["mechanism"] is not None and rms["quadratic"] is not None
                                       and rms["mechanism"] < rms["quadratic"])
    section["chosen"] = "mechanism" if use_mech else "quadratic"
    if not use_mech:
        return quadratic, section
    lm = linkmap_from_mechanism(fit.mechanism, head, provenance={**quadratic.provenance, "model": "mechanism",
                                                                  "mechanism": str(spec.source)})
    Pt = np.random.default_rng(1).uniform([a.min for a in head.actuators], [a.max for a in head.actuators],
                                          (40, len(names)))
    truth, pred = fit.mechanism.link_poses_many(names, Pt), lm.predict(Pt)
    section["map_vs_mechanism_max_mm"] = max(
        float(np.max(np.linalg.norm(truth[n][:, :3, 3] - pred[n][:, :3], axis=1))) * 1e3 for n in truth)
    return lm, section
