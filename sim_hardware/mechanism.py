"""The emulated sample head's "real" mechanism: its mechanism file (:mod:`models.mechanism`) with perturbations.

Each motor has a mounting error (its encoder zero is off by a small angle) and hard stops a little beyond the
configured limits, so calibration can discover zero offsets and travel limits; the simulated tracker
(:mod:`sim_hardware.tracker`) observes this mechanism.
"""

from __future__ import annotations

import math

import numpy as np

from models.headspec import HeadSpec
from models.mechanism import SAMPLE_MECHANISM, Mechanism, load_mechanism


def sample_mechanism(
    head: HeadSpec | None = None,
    seed: int = 5,
    zero_error_deg: float = 1.5,
    stop_margin_deg: float = 4.0,
) -> Mechanism:
    """The sample head's mechanism (13 motors, 12 links) with seeded zero errors and hard stops.

    ``head`` names the mechanism file (``[paths] mechanism``; default the sample head's) and sets the hard stops
    ``stop_margin_deg`` beyond its configured limits (default: the sample head's limits built in); ``seed`` draws
    each motor's zero error within ±``zero_error_deg``.
    """
    path = head.path("mechanism") if head is not None else None
    mech = Mechanism(load_mechanism(path or SAMPLE_MECHANISM))
    deg = math.pi / 180.0
    rng = np.random.default_rng(seed)
    limits = _limits(head)
    for name in mech.actuators:
        mech.zero_error[name] = float(rng.uniform(-zero_error_deg, zero_error_deg)) * deg
        lo, hi = limits[name]
        mech.stops[name] = (lo - stop_margin_deg * deg, hi + stop_margin_deg * deg)
    return mech


_SAMPLE_LIMITS_DEG = {
    "jaw": (-2.0, 28.0), "upper_lip": (-20.0, 30.0), "lower_lip": (-20.0, 30.0),
    "cheek_l": (-25.0, 35.0), "cheek_r": (-25.0, 35.0), "brow_l": (-25.0, 35.0), "brow_r": (-25.0, 35.0),
    "lid_l": (-10.0, 45.0), "lid_r": (-10.0, 45.0),
    "lip_corner_l_up": (-30.0, 40.0), "lip_corner_l_back": (-30.0, 40.0),
    "lip_corner_r_up": (-30.0, 40.0), "lip_corner_r_back": (-30.0, 40.0),
}


def _limits(head: HeadSpec | None) -> dict[str, tuple[float, float]]:
    if head is None:
        return {k: (math.radians(a), math.radians(b)) for k, (a, b) in _SAMPLE_LIMITS_DEG.items()}
    return {a.name: (a.min, a.max) for a in head.actuators}
