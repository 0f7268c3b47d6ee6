"""The control cycle's guard stage in one compiled call (the safety filter's constraints, then the strain guard's
limit) gives the same poses, verdicts and counts as the two stages called in turn."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from models.headspec import GroupSpec, load_head
from models.kernel_support import kernels_available
from models.strain_guard import StrainGuard
from runtime.core.guard import GuardState, guarded, guarded_by_stages
from runtime.safety import SafetyFilter

pytestmark = pytest.mark.skipif(not kernels_available(), reason="numba is not installed")

HEAD = load_head(Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml")


def _random_targets(rng: np.random.Generator, sf: SafetyFilter, n: int) -> np.ndarray:
    """Targets in and beyond the limits, some held (NaN), some groups pulled apart."""
    span = sf.hi - sf.lo
    X = rng.uniform(sf.lo - 0.2 * span, sf.hi + 0.2 * span, (n, len(sf.lo)))
    X[rng.random(X.shape) < 0.1] = np.nan
    return X


def test_the_compiled_constraints_are_the_safety_filters() -> None:
    """Groups of every kind and size (a three-member mirror with uneven gains, overlapping coupled groups), holds
    and out-of-range targets: the kernel's values are the filter's, bit for bit."""
    from models._cycle_kernels import constrain

    names = HEAD.actuator_names
    extra = (GroupSpec("trio", "mirror", names[5:8], (1.0, -0.5, 2.0), None),
             GroupSpec("wide", "coupled", names[0:4], (1.0, 1.0, 1.0, 1.0), 0.1))
    for head in (HEAD, dataclasses.replace(HEAD, groups=HEAD.groups + extra)):
        sf = SafetyFilter(head)
        rng = np.random.default_rng(3)
        current = rng.uniform(sf.lo, sf.hi, (300, len(sf.lo)))
        for x, q in zip(_random_targets(rng, sf, 300), current, strict=True):
            out = np.empty_like(x)
            constrain(x, q, sf.lo, sf.hi, *sf.groups, out)
            assert np.array_equal(out, sf.constrain(x.copy(), q))


def test_the_guard_stage_in_one_call_is_the_two_stages() -> None:
    """A run of cycles with the guard's state carried between them (its last accepted pose, verdict, count)."""
    guard = StrainGuard.for_head(HEAD)
    assert guard is not None and guard.compiled
    sf = SafetyFilter(HEAD)
    rng = np.random.default_rng(5)
    targets = _random_targets(rng, sf, 400)
    targets[::7] = np.nan  # all held: the constrained target is the last accepted pose
    one, two = GuardState(), GuardState()
    q = sf.neutral.copy()
    verdicts = set()
    for k, x in enumerate(targets):
        got = guarded(one, guard, sf, q, x.copy())
        ref = guarded_by_stages(two, guard, sf, q, x.copy())
        assert np.array_equal(got, ref), k
        assert (one.verdict, one.refused) == (two.verdict, two.refused), k
        assert np.array_equal(one.ok, two.ok), k
        verdicts.add(one.verdict)
        q = q + 0.3 * (got - q)  # the command follows part of the way, as the shaper would
    assert verdicts == {"ok", "limited", "held"}
