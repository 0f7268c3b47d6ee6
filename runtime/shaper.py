"""The one motion shaper: time-optimal, jerk-limited online trajectories (ruckig) toward each cycle's targets.

:class:`Shaper` keeps the commanded position, velocity and acceleration of N actuators (SI) and, once per control
cycle, advances them by ``dt`` along the time-optimal trajectory toward the latest targets under per-actuator
velocity, acceleration and jerk limits. It runs ruckig in online mode: one ``Ruckig`` instance with reused input and
output parameters, the current state taken from its own last output, a new trajectory computed only when a target
or a limit changes. A NaN target means hold: that actuator brakes to a stop as fast as its limits allow (ruckig's
velocity interface with target velocity 0) instead of being sent back to where it was. ``speed`` in (0, 1] scales
the velocity and acceleration limits (jerk stays, so slow moves keep short ramps). Targets are expected clipped to the
position limits already (the safety stage does that). Given ``lo``/``hi``, every newly computed plan is checked
against them (its position extrema; a plan from rest is not: it stays between where it starts and its targets,
which ``tests/runtime/test_shaper.py`` checks of ruckig on random plans), and an actuator whose plan would leave
them (possible only when a target arrives closer than its stopping distance right after limits shrank, or from a
reset state moving toward a limit) brakes at its full limits instead, which stops it before the target it was
moving toward; a position that would still leave them is clipped and counted in :attr:`clamps`.

A reset outside [lo, hi] (a motor found out of its range when the head enabled) keeps that position: the bound it
lies beyond is widened to it (:attr:`lo_now`, :attr:`hi_now`) and narrows back with every cycle's command, so the
actuator can only move back toward its range, at its limits, never further out (targets are clipped into [lo, hi]).
:attr:`outside` marks the actuators still out of range.

Jerk limit: per actuator, or by default ``amax / DEFAULT_JERK_TIME`` (full acceleration reached in 20 ms).
"""

from __future__ import annotations

import math

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, Synchronization

from models.headspec import HeadSpec

#: Default time to ramp from zero to full acceleration, seconds: jmax = amax / DEFAULT_JERK_TIME.
DEFAULT_JERK_TIME = 0.02


class ShaperError(RuntimeError):
    """Ruckig refused a state the shaper gave it (a bug, not bad input: input is checked before it gets there)."""


def _limit_array(name: str, value: float | np.ndarray, n: int) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy() if np.ndim(value) == 0 else \
        np.asarray(value, dtype=float).copy()
    if arr.shape != (n,):
        raise ValueError(f"{name} must be one value or {n} values, got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name} must be finite and positive, got {arr.tolist()}")
    return arr


def profile_extrema(profile) -> tuple[float, float]:
    """Exact position extrema of one DoF's ruckig ``Profile``: its brake pre-profile and its seven constant-jerk
    segments, each at its ends and where its velocity (a quadratic in time) crosses zero."""
    brake = profile.brake
    segments = []
    if brake.duration > 0.0:
        segments += zip(brake.t, brake.p, brake.v, brake.a, brake.j, strict=True)
    lo = hi = float(brake.p[0] if segments else profile.p[0])
    segments += zip(profile.t, profile.p[:7], profile.v[:7], profile.a[:7], profile.j, strict=True)
    for t, p, v, a, j in segments:
        if t <= 0.0:
            continue
        times = [t]
        if j != 0.0:  # v + a τ + j τ²/2 = 0
            disc = a * a - 2.0 * j * v
            if disc >= 0.0:
                root = math.sqrt(disc)
                times += [(-a - root) / j, (-a + root) / j]
        elif a != 0.0:
            times.append(-v / a)
        for tau in times:
            if 0.0 < tau <= t:
                x = p + tau * (v + tau * (a / 2.0 + tau * j / 6.0))
                lo, hi = min(lo, x), max(hi, x)
    return lo, hi


class Shaper:
    """Jerk-limited online trajectory shaping for N actuators (SI units; one :meth:`step` per control cycle)."""

    def __init__(self, vmax: np.ndarray, amax: np.ndarray, jmax: np.ndarray | None = None, dt: float = 0.004, *,
                 lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> None:
        vmax_arr = np.asarray(vmax, dtype=float)
        if vmax_arr.ndim != 1 or vmax_arr.size == 0:
            raise ValueError(f"vmax must be a 1-D array with one value per actuator, got shape {vmax_arr.shape}")
        n = vmax_arr.size
        if not (isinstance(dt, (int, float)) and np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        self.n = n
        self.dt = float(dt)
        self.vmax = _limit_array("vmax", vmax_arr, n)
        self.amax = _limit_array("amax", amax, n)
        self.jmax = _limit_array("jmax", self.amax / DEFAULT_JERK_TIME if jmax is None else jmax, n)
        self.lo = None if lo is None else np.asarray(lo, dtype=float).copy()
        self.hi = None if hi is None else np.asarray(hi, dtype=float).copy()
        #: The bounds commands keep to now: [lo, hi], widened to a reset position outside them (module docstring).
        self.lo_now, self.hi_now = self.lo, self.hi
        self._outside = False
        if (self.lo is None) != (self.hi is None):
            raise ValueError("give both lo and hi, or neither")
        if self.lo is not None and self.hi is not None and (
                self.lo.shape != (n,) or self.hi.shape != (n,) or not np.all(self.lo < self.hi)):
                raise ValueError(f"lo and hi must be {n} values each with lo < hi")
        self._otg = Ruckig(n, self.dt)
        self._inp = InputParameter(n)
        self._out = OutputParameter(n)
        self._inp.synchronization = Synchronization.No  # each actuator time-optimal on its own
        self._inp.max_jerk = self.jmax.tolist()
        self._position_iface = [ControlInterface.Position] * n
        self._speed = np.full(n, np.nan)
        self._target = np.full(n, np.nan)
        self._holding = np.zeros(n, dtype=bool)
        self.q = np.zeros(n)
        self._v: np.ndarray | None = np.zeros(n)  # None: as the ruckig input holds them (the properties v, a)
        self._a: np.ndarray | None = np.zeros(n)
        #: Cycles in which a plan was replaced by full-limit braking (see the module docstring).
        self.fallbacks = 0
        #: Cycles in which a position was clipped to the limits (last resort; 0 unless reset moving at a limit).
        self.clamps = 0
        self.reset(np.zeros(n) if self.lo is None else np.clip(np.zeros(n), self.lo, self.hi))

    @classmethod
    def from_head(cls, head: HeadSpec, dt: float, velocity_margin: float = 1.0) -> Shaper:
        """A shaper for a head: its actuators' limits, in actuator order.

        An actuator's ``options.max_jerk`` (config units per s³, e.g. deg/s³) sets its jerk limit; without it the
        default applies. ``velocity_margin`` scales the max velocities (the drivers refuse commands above them).
        """
        acts = head.actuators
        jerk = []
        for a in acts:
            raw = a.options.get("max_jerk") if a.options else None
            if raw is None:
                jerk.append(a.max_acceleration / DEFAULT_JERK_TIME)
            elif isinstance(raw, bool) or not isinstance(raw, (int, float)) or not raw > 0:
                raise ValueError(f"actuator {a.name!r}: options.max_jerk must be a positive number, got {raw!r}")
            else:
                jerk.append(float(raw) * a.unit_scale)
        return cls(np.array([a.max_velocity for a in acts]) * velocity_margin,
                   np.array([a.max_acceleration for a in acts]), np.array(jerk), dt,
                   lo=np.array([a.min for a in acts]), hi=np.array([a.max for a in acts]))

    def reset(self, q: np.ndarray, v: np.ndarray | float = 0.0) -> None:
        """Start from a measured state (on enable): positions ``q``, velocities ``v`` (default at rest)."""
        q = np.asarray(q, dtype=float)
        v_arr = np.broadcast_to(np.asarray(v, dtype=float), (self.n,))
        if q.shape != (self.n,) or not np.all(np.isfinite(q)) or not np.all(np.isfinite(v_arr)):
            raise ValueError(f"reset needs {self.n} finite positions and velocities, got {q.tolist()}, "
                             f"{v_arr.tolist()}")
        if self.lo is not None and self.hi is not None:
            tol = 1e-9 * np.maximum(1.0, self.hi - self.lo)  # rounding: clipped, not an actuator out of range
            q = np.where((q >= self.lo - tol) & (q <= self.hi + tol), np.clip(q, self.lo, self.hi), q)
            self.lo_now, self.hi_now = np.minimum(self.lo, q), np.maximum(self.hi, q)
            self._outside = bool(np.any(q < self.lo) or np.any(q > self.hi))
        self.q, self.v, self.a = q.copy(), v_arr.copy(), np.zeros(self.n)
        inp = self._inp
        inp.current_position = self.q.tolist()
        inp.current_velocity = self.v.tolist()
        inp.current_acceleration = self.a.tolist()
        inp.target_position = self.q.tolist()
        inp.target_velocity = [0.0] * self.n
        inp.target_acceleration = [0.0] * self.n
        self._target = self.q.copy()
        self._holding = np.zeros(self.n, dtype=bool)
        self._any_hold = False
        self._clamping = False
        self._replan = False
        inp.per_dof_control_interface = self._position_iface
        self._speed = np.full(self.n, np.nan)
        self._speed_scalar: float | None = None
        self._targets_key = b""
        self._at_rest = not self.v.any()  # every actuator at rest: a new plan stays between start and targets

    def step(self, targets: np.ndarray, speed: float | np.ndarray = 1.0, dt: float | None = None) -> np.ndarray:
        """Advance one cycle toward ``targets`` (SI, NaN = hold) at ``speed`` in (0, 1]; returns the new commands.

        ``dt`` (s, default :attr:`dt`) is how far this cycle advances along the plan: a cycle run ahead of its
        deadline advances only by the time that passed since the one before, so the limits hold in real time.
        Unchanged targets and speed cost only the sampling of the current plan (the common case between frames).
        """
        if dt is None:
            dt = self.dt
        if dt != self._otg.delta_time:
            if not (np.isfinite(dt) and dt > 0):
                raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
            self._otg.delta_time = float(dt)
        x = np.asarray(targets, dtype=float)
        key = x.tobytes()
        if key != self._targets_key or x.shape != (self.n,):
            self._set_targets(x)
            self._targets_key = key
        if isinstance(speed, (int, float)) and not isinstance(speed, bool):
            if speed != self._speed_scalar:
                self._set_speed(np.full(self.n, float(speed)))
                self._speed_scalar = speed
        else:
            self._set_speed(np.broadcast_to(np.asarray(speed, dtype=float), (self.n,)))
            self._speed_scalar = None
        inp, out = self._inp, self._out
        from_rest = self._at_rest
        result = self._otg.update(inp, out)
        if out.new_calculation:
            self._clamping = False
        if (out.new_calculation and not from_rest and self.lo is not None
                and (result == Result.Working or result == Result.Finished)):
            leaving = self._leaving_limits()
            if leaving.any():
                result = self._brake_fully(leaving)
        if result != Result.Working and result != Result.Finished:
            raise ShaperError(f"ruckig refused the trajectory ({result.name}) from q={self.q.tolist()}, "
                              f"v={self.v.tolist()}, a={self.a.tolist()} toward {x.tolist()}")
        if result == Result.Finished and not self._clamping:
            return self._arrive()
        q = np.array(out.new_position)
        if self._clamping:  # a braking plan that could not stay inside the limits (see the module docstring)
            self.v = np.array(out.new_velocity)
            self.a = np.array(out.new_acceleration)
            outside = (q < self.lo_now) | (q > self.hi_now)
            if outside.any():
                self.clamps += 1
                q = np.clip(q, self.lo_now, self.hi_now)
                self.v = np.where(outside, 0.0, self.v)
                self.a = np.where(outside, 0.0, self.a)
                inp.current_position, inp.current_velocity = q.tolist(), self.v.tolist()
                inp.current_acceleration = self.a.tolist()
            else:
                out.pass_to_input(inp)
        else:
            if self.lo_now is not None:  # rounding only: plans were checked against the limits
                np.maximum(q, self.lo_now, out=q)
                np.minimum(q, self.hi_now, out=q)
            out.pass_to_input(inp)
            self._v = self._a = None  # the plan's new velocity and acceleration, read from the input when asked
        self.q = q
        self._at_rest = False
        if self._outside:
            self._narrow()
        if self._any_hold:  # a held actuator stays where it stops
            self._target = np.where(self._holding, q, self._target)
        return q

    def _arrive(self) -> np.ndarray:
        """Every actuator is done: exactly at its target (held ones where they stopped), at rest, no rounding left."""
        if self._any_hold:
            stopped = np.array(self._out.new_position)
            if self.lo_now is not None:  # rounding only, as in step
                stopped = np.minimum(np.maximum(stopped, self.lo_now), self.hi_now)
            self._target = np.where(self._holding, stopped, self._target)
        if not (np.array_equal(self.q, self._target) and not self.v.any() and not self.a.any()):
            self.q = self._target.copy()
            self.v = np.zeros(self.n)
            self.a = np.zeros(self.n)
            inp = self._inp
            inp.current_position = self.q.tolist()
            inp.current_velocity = inp.current_acceleration = [0.0] * self.n
        self._at_rest = True
        if self._outside:
            self._narrow()
        return self.q

    @property
    def v(self) -> np.ndarray:
        """The commanded velocities (SI), as of the last cycle."""
        if self._v is None:
            self._v = np.array(self._inp.current_velocity)
        return self._v

    @v.setter
    def v(self, value: np.ndarray) -> None:
        self._v = value

    @property
    def a(self) -> np.ndarray:
        """The commanded accelerations (SI), as of the last cycle."""
        if self._a is None:
            self._a = np.array(self._inp.current_acceleration)
        return self._a

    @a.setter
    def a(self, value: np.ndarray) -> None:
        self._a = value

    @property
    def outside(self) -> np.ndarray:
        """Actuators whose command is still outside [lo, hi] (back from a reset outside them)."""
        if self.lo is None or self.hi is None or not self._outside:
            return np.zeros(self.n, dtype=bool)
        return (self.q < self.lo) | (self.q > self.hi)

    def _narrow(self) -> None:
        """Narrow the widened bounds to the command: what an actuator came back, it cannot go out again."""
        assert self.lo is not None and self.hi is not None and self.lo_now is not None and self.hi_now is not None
        self.lo_now = np.minimum(self.lo, np.maximum(self.lo_now, self.q))
        self.hi_now = np.maximum(self.hi, np.minimum(self.hi_now, self.q))
        self._outside = bool(np.any(self.lo_now < self.lo) or np.any(self.hi_now > self.hi))

    def _set_targets(self, x: np.ndarray) -> None:
        if x.shape != (self.n,):
            raise ValueError(f"targets must have shape ({self.n},), got {x.shape}")
        # One reduction tells the usual case (every target a number: their sum is finite); only then are the NaN
        # (hold) and infinite targets told apart.
        all_finite = math.isfinite(float(np.add.reduce(x)))
        if not all_finite and np.any(np.isinf(x)):
            raise ValueError("targets must be finite or NaN (hold)")
        inp = self._inp
        if not (self._any_hold or self._replan or not all_finite):  # the streaming case: every actuator targeted
            if self.lo is not None:
                x = np.minimum(np.maximum(x, self.lo), self.hi)  # np.clip costs twice as much on 13 values
            self._target = x
            inp.target_position = x.tolist()
            return
        # Few array operations on this path: it runs on every cycle a held target set changes (a show-control
        # input addressing some channels), before the cycle's post (in the running loop, 97 -> 65 µs).
        hold = x != x  # NaN: hold
        if self.lo is not None and self.hi is not None:
            x = np.minimum(np.maximum(x, self.lo), self.hi)  # NaN stays NaN
        hold_changed = self._replan or hold.tobytes() != self._holding.tobytes()
        self._replan = False
        if hold_changed:
            self._holding = hold
            self._any_hold = bool(hold.any())
            inp.per_dof_control_interface = [ControlInterface.Velocity if h else ControlInterface.Position
                                             for h in hold.tolist()]
        target = np.where(hold, self._target, x)
        if hold_changed or target.tobytes() != self._target.tobytes():
            self._target = target
            inp.target_position = np.where(hold, self.q, target).tolist()

    def _set_speed(self, s: np.ndarray) -> None:
        if np.array_equal(s, self._speed):
            return
        if not np.all((s > 0) & (s <= 1)):
            raise ValueError(f"speed must lie in (0, 1], got {s.tolist()}")
        self._speed = s.copy()
        self._inp.max_velocity = (self.vmax * s).tolist()
        self._inp.max_acceleration = (self.amax * s).tolist()

    def _leaving_limits(self) -> np.ndarray:
        """Actuators whose newly computed plan leaves [lo, hi] (beyond a rounding tolerance)."""
        assert self.lo is not None and self.hi is not None and self.lo_now is not None and self.hi_now is not None
        ext = self._out.trajectory.position_extrema
        tol = 1e-9 * np.maximum(1.0, self.hi - self.lo)
        floor = (self.lo_now - tol).tolist()
        ceil = (self.hi_now + tol).tolist()
        if all(e.min >= f and e.max <= c for e, f, c in zip(ext, floor, ceil, strict=True)):
            return np.zeros(self.n, dtype=bool)  # the usual case, told without building arrays of the extrema
        lo = np.array([e.min for e in ext])
        hi = np.array([e.max for e in ext])
        leaving = (lo < self.lo_now - tol) | (hi > self.hi_now + tol)
        # ruckig (0.19) reports a velocity-interface (braking) DoF's extrema as a range around the true one (0.0 and
        # an earlier plan's values can be in it): never too small, but a false alarm on a range that excludes them.
        # Those DoFs are checked again on their own profile.
        braking = [c == ControlInterface.Velocity for c in self._inp.per_dof_control_interface]
        for i in np.flatnonzero(leaving).tolist():
            if braking[i]:
                p_min, p_max = profile_extrema(self._out.trajectory.profiles[0][i])
                leaving[i] = p_min < floor[i] or p_max > ceil[i]
        return leaving

    def _brake_fully(self, which: np.ndarray) -> Result:
        """Replan ``which`` actuators as a stop at their full (unscaled) limits; the others keep their plans."""
        self.fallbacks += 1
        inp = self._inp
        inp.max_velocity = np.where(which, self.vmax, self.vmax * self._speed).tolist()
        inp.max_acceleration = np.where(which, self.amax, self.amax * self._speed).tolist()
        braking = self._holding | which
        inp.per_dof_control_interface = [ControlInterface.Velocity if b else ControlInterface.Position
                                         for b in braking]
        # The next step sets every limit, control interface and target again.
        self._speed = np.full(self.n, np.nan)
        self._speed_scalar = None
        self._replan = True
        self._targets_key = b""
        result = self._otg.update(inp, self._out)
        self._clamping = bool(self._leaving_limits().any()) if result in (Result.Working, Result.Finished) else False
        return result
