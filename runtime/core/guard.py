"""The skin-strain guard stage: this cycle's target, whatever its source, kept to what the skin can take.

A target whose strain the skin cannot take is pulled back toward the last accepted one by bisection (or that one is
held). The guard's reduced check lives in :mod:`models.strain_guard`; this stage keeps what it needs between cycles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from runtime.safety import SafetyFilter

#: Bisections of the strain guard toward a refused target, per cycle.
GUARD_BISECTIONS = 3


class StrainLimiter(Protocol):
    """The skin-strain guard as the core calls it (:class:`models.strain_guard.StrainGuard`)."""

    compiled: bool  # limit_constrained is available (the measure is compiled)

    def limit(self, p_from: np.ndarray, p_to: np.ndarray, steps: int = ...) -> tuple[np.ndarray, str]:
        """The furthest pose from ``p_from`` toward ``p_to`` the skin takes, and the verdict (``"ok"`` when
        ``p_to`` itself passes)."""
        ...

    def limit_constrained(self, targets: np.ndarray, current: np.ndarray, p_from: np.ndarray, lo: np.ndarray,
                          hi: np.ndarray, groups: tuple[np.ndarray, np.ndarray], steps: int = ...
                          ) -> tuple[np.ndarray, str | None]:
        """``targets`` constrained (limits, groups, holds from ``current``), then :meth:`limit` from ``p_from`` in
        one call; verdict None when the constrained target is ``p_from`` itself."""
        ...


@dataclass
class GuardState:
    """The last target the guard accepted (None: start from the command), its verdict, how many it refused."""

    ok: np.ndarray | None = None
    verdict: str = "ok"
    refused: int = 0  # targets limited or held since start


def guarded(g: GuardState, limiter: StrainLimiter, safety: SafetyFilter, q: np.ndarray,
            targets: np.ndarray) -> np.ndarray:
    """``targets`` constrained to the groups and limits (against the command ``q``), then kept to what the skin
    takes: in one compiled call where the guard has one (:meth:`models.strain_guard.StrainGuard.limit_constrained`,
    the same poses and verdicts as :func:`guarded_by_stages`)."""
    if g.ok is None:
        g.ok = q.copy()
    if not limiter.compiled:
        return guarded_by_stages(g, limiter, safety, q, targets)
    p, verdict = limiter.limit_constrained(targets, q, g.ok, safety.lo, safety.hi, safety.groups,
                                           steps=GUARD_BISECTIONS)
    if verdict is None:
        return p
    g.ok = p
    if verdict != "ok":
        g.refused += 1
    g.verdict = verdict
    return p


def guarded_by_stages(g: GuardState, limiter: StrainLimiter, safety: SafetyFilter, q: np.ndarray,
                      targets: np.ndarray) -> np.ndarray:
    """:func:`guarded` as the safety filter's constraints, then the guard's limit (the reference)."""
    x = safety.constrain(targets, q)
    if g.ok is None:
        g.ok = q.copy()
    if np.array_equal(x, g.ok):
        return x
    # Three bisections: the furthest passing point within 1/8 of this cycle's (short) step; the segment between
    # two constrained poses stays constrained (groups and limits are convex), so the result needs no second pass.
    p, verdict = limiter.limit(g.ok, x, steps=GUARD_BISECTIONS)
    g.ok = p
    if verdict != "ok":
        g.refused += 1
    g.verdict = verdict
    return p


def judge_afresh(g: GuardState) -> None:
    """A new pose is judged afresh: the previous pose's "limited" must not make this one look settled before the
    guard has seen it (``pose_settled`` reads the verdict of the pose in hand)."""
    g.verdict = "ok"


def forget(g: GuardState) -> None:
    """Start afresh from the command (enable, fault, e-stop, reset)."""
    g.ok = None
