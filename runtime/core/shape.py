"""The shape stage: constrained targets → the command posted this cycle, through the jerk-limited shaper
(:mod:`runtime.shaper`, ruckig) to velocity, acceleration and jerk limits.

The shaper is this stage's state (commanded position, velocity, acceleration); groups and limits come from the
head's :class:`~runtime.safety.SafetyFilter`.
"""

from __future__ import annotations

import numpy as np

from models.headspec import HeadSpec
from runtime.safety import VELOCITY_MARGIN, SafetyFilter
from runtime.shaper import Shaper


def make_shaper(head: HeadSpec, period: float) -> Shaper:
    """The head's shaper at its neutral pose."""
    shaper = Shaper.from_head(head, dt=period, velocity_margin=VELOCITY_MARGIN)
    shaper.reset(np.array([a.neutral for a in head.actuators]))
    return shaper


def shape(shaper: Shaper, x: np.ndarray, speed: float, hold: np.ndarray, safe_speed: float = 1.0,
          dt: float | None = None) -> np.ndarray:
    """The shaper on constrained targets ``x``, advanced by ``dt`` (default one period): an actuator told to hold
    (``hold``) whose constrained target is just its present command brakes to a stop where it is instead of being
    sent back there. An actuator still outside its limits (enabled where it stood out of range) moves back at no
    more than ``safe_speed``."""
    if hold.any():
        x = np.where(hold & (x == shaper.q), np.nan, x)
    outside = shaper.outside
    if outside.any():
        return shaper.step(x, np.where(outside, min(speed, safe_speed), speed), dt).copy()
    return shaper.step(x, speed, dt).copy()


def advance(period: float, t: float, last: float | None) -> float:
    """How far the shaper advances in a cycle at ``t`` after one at ``last``: one period, or the time that passed
    when that is clearly less (a cycle run ahead of its deadline on an input's arrival; deadlines a period apart give
    exactly one period whatever their rounding); never more than a period, so a late cycle does not catch up."""
    if last is None or t - last >= 0.999 * period:
        return period
    return max(t - last, 1e-5)


def restart(shaper: Shaper, safety: SafetyFilter, measured: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
    """Start commanding from where the head is: the positions the buses hold since they enabled (``held``: the
    drivers measure the first target's step against them), else the measured positions; the last command where
    neither is known. Starting from positions measured a few milliseconds after the hold would make any motion in
    between (a motor settling or still coasting) a step the drivers refuse as too fast. A position outside the
    limits is kept, not clipped (a clipped start would be a jump the drivers refuse): the shaper then brings that
    actuator back into range at its limits and never further out. Returns the mask of actuators outside them."""
    q = np.where(np.isfinite(measured), measured, shaper.q)
    if held is not None:
        q = np.where(np.isfinite(held), held, q)
    shaper.reset(q)
    return (q < safety.lo) | (q > safety.hi)
