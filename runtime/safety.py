"""Always-on motion safety: position limits, group constraints, and velocity/acceleration shaping of every command.

:class:`SafetyFilter` keeps the commanded position and velocity of each actuator and moves them toward the requested
targets no faster than the actuator's max velocity (scaled down for pose and neutral moves) and acceleration, braking
in time to stop at the target. Whatever comes in (NaN, out-of-range, jumps), what comes out lies inside the limits
and within the rate limits. Watchdog, e-stop and fault reactions live in the daemon, which feeds this filter.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from models.headspec import HeadSpec
from models.kernel_args import pack_constraints

#: Commanded speed stays this fraction below the configured max velocity (the drivers refuse anything above it).
VELOCITY_MARGIN = 0.95


class SafetyFilter:
    """Limits, group constraints and a second-order rate limiter over the actuators of one head (SI)."""

    def __init__(self, head: HeadSpec) -> None:
        self.names: tuple[str, ...] = head.actuator_names
        self.index = {n: i for i, n in enumerate(self.names)}
        acts = head.actuators
        self.lo = np.array([a.min for a in acts])
        self.hi = np.array([a.max for a in acts])
        self.neutral = np.array([a.neutral for a in acts])
        self.vmax = np.array([a.max_velocity for a in acts]) * VELOCITY_MARGIN
        self.amax = np.array([a.max_acceleration for a in acts])
        self._together: list[tuple[np.ndarray, np.ndarray]] = []
        self._coupled: list[tuple[np.ndarray, float]] = []
        for g in head.groups:
            idx = np.array([self.index[m] for m in g.actuators])
            if g.kind in ("together", "mirror"):
                self._together.append((idx, np.array(g.gains, dtype=float)))
            elif g.max_spread is not None:
                self._coupled.append((idx, g.max_spread))
        self.groups = pack_constraints(head)  # the same groups, as the compiled guard stage reads them
        self.q = self.neutral.copy()
        self.v = np.zeros(len(self.names))

    def reset(self, positions: Mapping[str, float]) -> None:
        """Start from measured positions at rest (on enable)."""
        for n, p in positions.items():
            i = self.index.get(n)
            if i is not None and np.isfinite(p):
                self.q[i] = min(max(p, self.lo[i]), self.hi[i])
        self.v[:] = 0.0

    def vector(self, targets: Mapping[str, float]) -> np.ndarray:
        """Targets by name → vector with NaN for actuators not addressed (hold)."""
        x = np.full(len(self.names), np.nan)
        for n, val in targets.items():
            i = self.index.get(n)
            if i is not None:
                x[i] = val
        return x

    def constrain(self, x: np.ndarray, current: np.ndarray | None = None) -> np.ndarray:
        """Fill holds with the current command (``current``, default this filter's), apply group constraints, clip
        to position limits."""
        x = np.where(np.isfinite(x), x, self.q if current is None else current)
        for idx, gains in self._together:  # the reductions called directly: np.mean's, min's wrappers cost more
            common = float(np.add.reduce(x[idx] / gains)) / len(idx)  # the mean, to the bit
            x[idx] = gains * common
        for idx, spread in self._coupled:
            sub = x[idx]
            lo, hi = float(np.minimum.reduce(sub)), float(np.maximum.reduce(sub))
            if hi - lo > spread:
                mid = 0.5 * (lo + hi)
                x[idx] = mid + (sub - mid) * (spread / (hi - lo))
        return np.clip(x, self.lo, self.hi)

    def step(self, targets: np.ndarray, dt: float | np.ndarray, speed: float | np.ndarray = 1.0) -> np.ndarray:
        """Advance the commands by ``dt`` seconds (one value, or one per actuator) toward ``targets`` (NaN: hold);
        returns the new commands."""
        dt = np.maximum(np.asarray(dt, dtype=float), 1e-6)
        x = self.constrain(np.asarray(targets, dtype=float).copy())
        vmax = self.vmax * speed
        amax = self.amax * np.sqrt(speed)
        err = x - self.q
        # Fastest speed that still stops at the target, capped by max velocity and by reaching it this cycle.
        v_stop = np.sqrt(2.0 * amax * np.abs(err))
        v_des = np.sign(err) * np.minimum(np.minimum(np.abs(err) / dt, v_stop), vmax)
        dv = np.clip(v_des - self.v, -amax * dt, amax * dt)
        v = np.clip(self.v + dv, -vmax, vmax)
        q = self.q + v * dt
        clipped = (q < self.lo) | (q > self.hi)
        q = np.clip(q, self.lo, self.hi)
        v = np.where(clipped, 0.0, v)
        bad = ~np.isfinite(q)
        if bad.any():  # can only come from a corrupted state: hold, never pass it on
            q = np.where(bad, self.q, q)
            v = np.where(bad, 0.0, v)
        self.q, self.v = q, v
        return q

    def commands(self) -> dict[str, float]:
        """Current commands by actuator name."""
        return {n: float(x) for n, x in zip(self.names, self.q, strict=True)}
