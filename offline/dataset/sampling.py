"""Actuator sampling for pose datasets, as in the paper: uniform within range or boundary values at random.

Every pose honours the head's group constraints (``together``: equal values, ``mirror``: value times the gain
ratio, ``coupled``: members within ``max_spread`` of each other), duplicates are removed, and the result is
reproducible from the seed.
"""

from __future__ import annotations

import numpy as np


def _apply_groups(p: np.ndarray, head, index: dict[str, int], lo: np.ndarray, hi: np.ndarray) -> None:
    for g in head.groups:
        idx = [index[n] for n in g.actuators]
        first = idx[0]
        if g.kind == "together":
            for j in idx[1:]:
                p[j] = p[first]
        elif g.kind == "mirror":
            for j, gain in zip(idx[1:], g.gains[1:], strict=True):
                p[j] = p[first] * gain / g.gains[0]
        elif g.kind == "coupled" and g.max_spread is not None:
            s = g.max_spread
            for j in idx[1:]:
                p[j] = min(max(p[j], p[first] - s), p[first] + s)
            vals = p[idx]
            if vals.max() - vals.min() > s:
                p[idx] = np.clip(vals, vals.max() - s, vals.max())
        p[idx] = np.clip(p[idx], lo[idx], hi[idx])


def sample_ranges(head, range_fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-actuator sampling range (SI): the head's [min, max], or ``range_fraction`` of its span on each side of
    neutral, cut to [min, max] (for skins that only converge near neutral)."""
    if not 0.0 < range_fraction <= 1.0:
        raise ValueError(f"range fraction must lie in (0, 1], got {range_fraction}")
    lo = np.array([a.min for a in head.actuators])
    hi = np.array([a.max for a in head.actuators])
    if range_fraction < 1.0:
        neutral = np.array([a.neutral for a in head.actuators])
        half = range_fraction * (hi - lo)
        lo, hi = np.maximum(lo, neutral - half), np.minimum(hi, neutral + half)
    return lo, hi


def sample_poses(head, n: int, seed: int = 0, boundary_prob: float = 0.25, decimals: int = 9,
                 max_rounds: int = 100, range_fraction: float = 1.0) -> np.ndarray:
    """``n`` distinct actuator vectors (n, A), SI, in the head's actuator order.

    Each actuator is drawn uniformly within its :func:`sample_ranges` range, or with probability ``boundary_prob``
    set to that range's min or max (picked at random); group constraints are then applied and exact duplicates
    (after rounding to ``decimals``) dropped and redrawn.
    """
    if n < 1:
        raise ValueError(f"number of poses must be positive, got {n}")
    if not 0.0 <= boundary_prob <= 1.0:
        raise ValueError(f"boundary probability must lie in [0, 1], got {boundary_prob}")
    rng = np.random.default_rng(seed)
    lo, hi = sample_ranges(head, range_fraction)
    index = {a.name: i for i, a in enumerate(head.actuators)}
    n_act = len(lo)
    out: list[np.ndarray] = []
    seen: set[bytes] = set()
    for _ in range(max_rounds):
        need = n - len(out)
        if need <= 0:
            break
        draw = need + need // 4 + 8
        uni = lo + rng.random((draw, n_act)) * (hi - lo)
        at_bound = rng.random((draw, n_act)) < boundary_prob
        bound = np.where(rng.random((draw, n_act)) < 0.5, lo, hi)
        cand = np.where(at_bound, bound, uni)
        for row in cand:
            _apply_groups(row, head, index, lo, hi)
            key = np.round(row, decimals).tobytes()
            if key in seen:
                continue
            seen.add(key)
            out.append(row)
            if len(out) == n:
                break
    if len(out) < n:
        raise ValueError(f"only {len(out)} distinct poses exist for these settings; asked for {n}")
    return np.array(out)
