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


def shape(shaper: Shaper, x: np.ndarray, speed: float, hold: np.ndarray) -> np.ndarray:
    """The shaper on constrained targets ``x``: an actuator told to hold (``hold``) whose constrained target is just
    its present command brakes to a stop where it is instead of being sent back there."""
    if hold.any():
        x = np.where(hold & (x == shaper.q), np.nan, x)
    return shaper.step(x, speed).copy()


def restart(shaper: Shaper, safety: SafetyFilter, measured: np.ndarray) -> None:
    """Start commanding from where the head is (its measured positions, within limits; the last command where
    nothing was measured)."""
    q = np.where(np.isfinite(measured), measured, shaper.q)
    shaper.reset(np.clip(q, safety.lo, safety.hi))
