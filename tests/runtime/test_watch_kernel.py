"""The following-error watch compiled (``models._cycle_kernels.following_watch``) against its numpy reference: the
same errors, peaks, times and findings over random runs with commands not yet posted, unmeasured actuators, late
buses and actuators that stay beyond their limits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.headspec import load_head
from models.kernel_support import kernels_available
from runtime.config import daemon_config
from runtime.core.watch import WatchParams, WatchState, check_following, post
from tests.runtime.conftest import SAMPLE

pytestmark = pytest.mark.skipif(not kernels_available(), reason="numba is not installed: the watch runs in numpy")


def test_the_compiled_watch_is_the_numpy_watch() -> None:
    head = load_head(SAMPLE)
    names = head.actuator_names
    bus_names = tuple(head.buses)
    buses = tuple((b, np.array([i for i, a in enumerate(head.actuators) if a.bus == b])) for b in bus_names)
    bus_of = tuple(a.bus for a in head.actuators)
    wp = WatchParams.build(head, daemon_config(head, {}), bus_names, 0.004)
    wp = dataclasses.replace(wp, max_error=np.full(len(names), 0.05), error_time_s=np.full(len(names), 0.02))
    rng = np.random.default_rng(5)
    n = len(names)
    fast, ref = WatchState.initial(n), WatchState.initial(n)
    scale, units = np.ones(n), tuple("rad" for _ in names)
    findings = 0
    for k in range(3000):
        t = 10.0 + 0.004 * k
        write = None if k % 17 == 3 else rng.normal(0.0, 0.1, n)
        post(fast, write)
        post(ref, write)
        measured = (write if write is not None else np.zeros(n)) + rng.normal(0.0, 0.03, n)
        if k % 100 < 30:  # an actuator that stops following for a while
            measured[(k // 100) % n] += 0.3
        measured[rng.random(n) < 0.05] = np.nan
        ages = [float(a) for a in rng.choice([0.001, 0.5], size=len(bus_names), p=[0.9, 0.1])]
        got = check_following(fast, wp, names, buses, bus_of, ages, measured.copy(), scale, units, t, compiled=True)
        want = check_following(ref, wp, names, buses, bus_of, ages, measured.copy(), scale, units, t, compiled=False)
        assert got == want, k
        findings += want is not None
        for a, b in ((fast.error, ref.error), (fast.peak_error, ref.peak_error), (fast.over_since, ref.over_since)):
            assert np.array_equal(a, b, equal_nan=True), k
        if k % 250 == 0:  # start afresh now and then, as an enable does
            fast.restart()
            ref.restart()
    assert findings > 10
