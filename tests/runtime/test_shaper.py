"""Shaper: whatever the targets, commands stay inside the position, velocity and acceleration limits and settle."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.headspec import load_head
from runtime.shaper import DEFAULT_JERK_TIME, Shaper

ROOT = Path(__file__).resolve().parents[2]
HEAD = ROOT / "heads" / "sample" / "head.toml"
DT = 0.004
REL = 1e-9

LO = np.array([-0.5, -0.02, 0.0])
HI = np.array([0.7, 0.03, 1.2])
VMAX = np.array([3.0, 0.1, 2.0])
AMAX = np.array([40.0, 1.5, 10.0])


def make(jmax=None) -> Shaper:
    return Shaper(VMAX, AMAX, jmax, DT, lo=LO, hi=HI)


def check_state(sh: Shaper, speed: np.ndarray, prev_q: np.ndarray) -> None:
    assert np.all(sh.q >= sh.lo) and np.all(sh.q <= sh.hi), sh.q
    assert np.all(np.abs(sh.v) <= sh.vmax * speed * (1 + REL)), (sh.v, sh.vmax * speed)
    assert np.all(np.abs(sh.a) <= sh.amax * speed * (1 + REL)), (sh.a, sh.amax * speed)
    # the commanded positions themselves move no faster than the velocity limit
    assert np.all(np.abs(sh.q - prev_q) <= sh.vmax * speed * DT * (1 + REL) + 1e-15)


def settle_cycles(sh: Shaper, speed: np.ndarray) -> int:
    """An upper bound on the cycles any rest-to-rest or braking-then-move motion needs, with margin."""
    v, a = sh.vmax * speed, sh.amax * speed
    t = (sh.hi - sh.lo) / v + 3 * v / a + 6 * a / sh.jmax
    return int(np.ceil(t.max() / DT)) + 50


target_value = st.one_of(
    st.floats(-2.0, 2.0),  # often out of range: the shaper clips
    st.just(float("nan")),  # hold
    st.sampled_from([-0.5, 0.7, 0.03, -0.02, 0.0, 1.2]),  # exactly at the limits
)
segment = st.tuples(st.lists(target_value, min_size=3, max_size=3), st.integers(1, 60))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(segments=st.lists(segment, min_size=1, max_size=8), speed=st.floats(0.2, 1.0),
       start=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
       final=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3))
def test_any_target_sequence_stays_in_limits_and_settles(segments, speed, start, final):
    sh = make()
    sh.reset(LO + np.array(start) * (HI - LO))
    s = np.full(3, speed)
    prev = sh.q.copy()
    for values, cycles in segments:  # jumps, reversals, holds and out-of-range values, held for a few cycles each
        targets = np.array(values)
        for _ in range(cycles):
            sh.step(targets, speed)
            check_state(sh, s, prev)
            prev = sh.q.copy()
    goal = np.clip(LO + np.array(final) * (HI - LO), LO, HI)
    for _ in range(settle_cycles(sh, s)):
        sh.step(goal, speed)
        check_state(sh, s, prev)
        prev = sh.q.copy()
    np.testing.assert_array_equal(sh.q, goal)  # exactly there, at rest
    assert np.all(sh.v == 0) and np.all(sh.a == 0)
    assert sh.clamps == 0


@settings(max_examples=40, deadline=None)
@given(frac=st.floats(0.0, 1.0), run_cycles=st.integers(5, 80), to_limit=st.booleans())
def test_target_change_mid_motion_never_passes_a_limit(frac, run_cycles, to_limit):
    sh = make()
    sh.reset(LO.copy())
    far = HI.copy()
    prev = sh.q.copy()
    for _ in range(run_cycles):  # accelerate toward the upper limit
        sh.step(far)
        check_state(sh, np.ones(3), prev)
        prev = sh.q.copy()
    # a new target just ahead of the moving command (closer than its stopping distance), or back toward the start
    new = HI if to_limit else sh.q + frac * (HI - sh.q)
    peak = sh.q.copy()
    for _ in range(settle_cycles(sh, np.ones(3))):
        sh.step(new)
        check_state(sh, np.ones(3), prev)
        prev = sh.q.copy()
        peak = np.maximum(peak, sh.q)
    np.testing.assert_allclose(sh.q, new, atol=1e-12)
    assert np.all(peak <= HI)
    assert sh.clamps == 0


def test_slowing_down_mid_motion_brakes_within_the_full_limits():
    sh = make()
    sh.reset(LO.copy())
    for _ in range(60):
        sh.step(HI)
    assert np.any(np.abs(sh.v) > 0.5 * VMAX)
    prev_speed = np.abs(sh.v)
    for _ in range(settle_cycles(sh, np.full(3, 0.1))):
        sh.step(HI, 0.1)
        assert np.all(sh.q <= HI) and np.all(sh.q >= LO)
        assert np.all(np.abs(sh.a) <= AMAX * (1 + REL))
        # above the new limit the speed only falls; below it, it stays below it
        over = prev_speed > VMAX * 0.1 * (1 + REL)
        assert np.all(np.abs(sh.v)[over] <= prev_speed[over] * (1 + REL))
        assert np.all(np.abs(sh.v)[~over] <= VMAX[~over] * 0.1 * (1 + REL))
        prev_speed = np.abs(sh.v)
    np.testing.assert_allclose(sh.q, HI, atol=1e-12)
    assert sh.clamps == 0


def test_hold_brakes_to_a_stop_without_going_back():
    sh = make()
    sh.reset(LO.copy())
    for _ in range(40):
        sh.step(HI)
    moving = sh.q.copy()
    last = sh.q.copy()
    hold = np.array([np.nan, HI[1], np.nan])
    for _ in range(200):
        sh.step(hold)
        assert np.all(sh.q[[0, 2]] >= last[[0, 2]])  # never reverses toward where it was
        last = sh.q.copy()
    assert sh.v[0] == 0 and sh.v[2] == 0
    assert np.all(sh.q[[0, 2]] > moving[[0, 2]]) and np.all(sh.q[[0, 2]] < HI[[0, 2]])
    np.testing.assert_allclose(sh.q[1], HI[1], atol=1e-12)
    stopped = sh.q.copy()
    for _ in range(50):  # and stays there while held
        sh.step(hold)
    np.testing.assert_array_equal(sh.q[[0, 2]], stopped[[0, 2]])


def test_reset_moving_toward_a_limit_brakes_and_stays_inside():
    sh = make()
    sh.reset(HI - 0.001 * (HI - LO), v=VMAX)  # at full speed just short of the upper limit: cannot stop in time
    for _ in range(200):
        sh.step(HI)
        assert np.all(sh.q <= HI) and np.all(np.abs(sh.a) <= AMAX * (1 + REL))
    np.testing.assert_allclose(sh.q, HI, atol=1e-12)
    assert sh.fallbacks > 0


def test_jerk_limit_default_and_per_actuator_option():
    sh = make()
    np.testing.assert_allclose(sh.jmax, AMAX / DEFAULT_JERK_TIME)
    head = load_head(HEAD)
    acts = list(head.actuators)
    jaw = dataclasses.replace(acts[0], options={**acts[0].options, "max_jerk": 20000.0})  # deg/s³ on the jaw
    sh = Shaper.from_head(dataclasses.replace(head, actuators=(jaw, *acts[1:])), DT)
    assert sh.n == len(acts)
    assert sh.jmax[0] == pytest.approx(20000.0 * jaw.unit_scale)
    np.testing.assert_allclose(sh.jmax[1:], [a.max_acceleration / DEFAULT_JERK_TIME for a in acts[1:]])
    np.testing.assert_allclose(sh.lo, [a.min for a in acts])
    bad = dataclasses.replace(acts[0], options={"max_jerk": -1})
    with pytest.raises(ValueError, match="max_jerk"):
        Shaper.from_head(dataclasses.replace(head, actuators=(bad, *acts[1:])), DT)


def test_bad_input_is_refused_by_name():
    sh = make()
    with pytest.raises(ValueError, match="targets must have shape"):
        sh.step(np.zeros(4))
    with pytest.raises(ValueError, match="finite or NaN"):
        sh.step(np.array([np.inf, 0.0, 0.0]))
    for speed in (0.0, 1.5, -0.1, np.array([0.5, 0.5, 2.0])):
        with pytest.raises(ValueError, match="speed"):
            sh.step(np.zeros(3), speed)
    with pytest.raises(ValueError, match="vmax"):
        Shaper(np.array([1.0, -1.0]), np.ones(2), None, DT)
    with pytest.raises(ValueError, match="amax"):
        Shaper(np.ones(2), np.ones(3), None, DT)
    with pytest.raises(ValueError, match="dt"):
        Shaper(np.ones(2), np.ones(2), None, 0.0)
    with pytest.raises(ValueError, match="lo and hi"):
        Shaper(np.ones(2), np.ones(2), None, DT, lo=np.zeros(2), hi=np.zeros(2))
    with pytest.raises(ValueError, match="reset"):
        sh.reset(np.array([np.nan, 0.0, 0.0]))


@pytest.mark.parametrize("start, target", [(-0.9, -3.0), (1.6, 9.0), (-0.9, 0.5), (1.6, 0.1)])
def test_reset_outside_the_limits_moves_back_never_further_out(start: float, target: float) -> None:
    """A reset outside [lo, hi] (a motor enabled out of range) keeps that position; a hold keeps it there, any
    target (clipped into the range, even one further out) brings it back at the shaper's limits, monotonically,
    and the widened bound narrows behind it."""
    sh = make()
    q0 = np.array([0.0, 0.0, start])  # the third actuator's range is [0, 1.2]
    sh.reset(q0)
    assert sh.q[2] == start and sh.outside.tolist() == [False, False, True]
    for _ in range(20):  # a hold (NaN) stays where it stands: the core turns a hold into the nearest limit
        sh.step(np.full(3, np.nan))
    assert sh.q[2] == start
    x = np.array([np.nan, np.nan, target])
    prev = sh.q.copy()
    for _ in range(2000):
        sh.step(x)
        assert np.all(np.abs(sh.q - prev) <= sh.vmax * DT * (1 + REL) + 1e-15)
        side = np.sign(start - HI[2]) if start > HI[2] else -1.0
        assert side * (sh.q[2] - prev[2]) <= 1e-12  # only ever toward the range
        assert sh.lo_now[2] <= min(sh.q[2], LO[2]) and sh.hi_now[2] >= max(sh.q[2], HI[2])
        prev = sh.q.copy()
        if not sh.outside.any() and np.allclose(sh.v, 0.0):
            break
    assert not sh.outside.any()
    assert LO[2] <= sh.q[2] <= HI[2]
    assert sh.lo_now[2] == LO[2] and sh.hi_now[2] == HI[2]  # the bounds are the configured ones again
    sh.step(np.array([np.nan, np.nan, -5.0]))  # and a target outside is clipped as ever
    for _ in range(2000):
        sh.step(np.array([np.nan, np.nan, -5.0]))
    assert sh.q[2] == pytest.approx(LO[2])


def test_a_plan_from_rest_stays_between_its_start_and_its_targets() -> None:
    """The shaper checks a new plan against the limits only when it starts in motion: from rest, ruckig's plans
    (each actuator on its own, as the shaper plans, or time-synchronized; held actuators braking in the velocity
    interface) stay between where each actuator starts and its target. Random plans on the sample head's limits, at
    random speeds."""
    from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, Synchronization

    sh = Shaper.from_head(load_head(HEAD), DT)
    n, rng = sh.n, np.random.default_rng(3)
    for k in range(600):
        otg, inp, out = Ruckig(n, DT), InputParameter(n), OutputParameter(n)
        inp.synchronization = Synchronization.No if k % 2 else Synchronization.Time  # the shaper's, and ruckig's
        inp.max_velocity = (sh.vmax * rng.uniform(0.05, 1.0)).tolist()
        inp.max_acceleration = (sh.amax * rng.uniform(0.05, 1.0)).tolist()
        inp.max_jerk = sh.jmax.tolist()
        q, hold = rng.uniform(sh.lo, sh.hi), rng.random(n) < 0.4
        target = np.where(hold, q, rng.uniform(sh.lo, sh.hi))
        inp.current_position, inp.target_position = q.tolist(), target.tolist()
        inp.current_velocity = inp.current_acceleration = [0.0] * n
        inp.target_velocity = inp.target_acceleration = [0.0] * n
        inp.per_dof_control_interface = [ControlInterface.Velocity if h else ControlInterface.Position for h in hold]
        assert otg.update(inp, out) in (Result.Working, Result.Finished)
        traj = out.trajectory
        path = np.array([traj.at_time(t)[0] for t in np.linspace(0.0, traj.duration, 60)])  # (60, n) positions
        tol = 1e-12 * np.maximum(1.0, sh.hi - sh.lo)
        assert np.all(path >= np.minimum(q, target) - tol) and np.all(path <= np.maximum(q, target) + tol)
        moving = ~hold  # the position interface's extrema (a held actuator's are not reported from rest)
        ext = traj.position_extrema
        assert np.all(np.array([e.min for e in ext])[moving] >= np.minimum(q, target)[moving] - tol[moving])
        assert np.all(np.array([e.max for e in ext])[moving] <= np.maximum(q, target)[moving] + tol[moving])


def test_a_move_from_rest_skips_the_extrema_check_and_one_in_motion_does_not() -> None:
    sh = make()
    sh.reset(np.array([0.0, 0.0, 0.5]))
    calls = []
    check = sh._leaving_limits
    sh._leaving_limits = lambda: calls.append(1) or check()  # type: ignore[method-assign]
    sh.step(np.array([0.5, 0.02, 0.9]))  # from rest
    assert calls == []
    sh.step(np.array([-0.4, 0.02, 0.9]))  # a new target while moving: checked
    assert calls == [1]
    for _ in range(settle_cycles(sh, np.ones(3))):
        sh.step(np.array([-0.4, 0.02, 0.9]))
    assert np.array_equal(sh.q, [-0.4, 0.02, 0.9]) and not sh.v.any()
    sh.step(np.array([0.6, -0.01, 0.1]))  # at rest again after arriving: not checked
    assert calls == [1]


def test_a_hold_on_a_range_that_excludes_zero_brakes_on_its_own_plan() -> None:
    """ruckig counts 0.0 (and an earlier plan's values) among the extrema of a velocity-interface (held) actuator; on
    a range that excludes them that false bound must not turn a hold into a full-limit brake."""
    lo, hi = np.array([0.2, 0.2]), np.array([1.0, 1.0])
    sh = Shaper(np.array([1.0, 1.0]), np.array([4.0, 4.0]), dt=0.002, lo=lo, hi=hi)
    sh.reset(np.array([0.5, 0.8]), v=np.array([0.5, -0.5]))  # moving (found so on enable), far from the limits
    for _ in range(300):
        sh.step(np.array([np.nan, np.nan]), speed=0.5)  # held: each brakes where it is, at half the limits
    assert sh.fallbacks == 0 and sh.clamps == 0
    assert not sh.v.any() and sh.q[0] > 0.5 and sh.q[1] < 0.8
    assert sh.q[0] == pytest.approx(0.5 + 0.5**2 / (2 * 2.0), abs=0.01)  # stopped at half the acceleration


def test_a_hold_that_would_carry_past_a_limit_brakes_at_full_limits() -> None:
    """A hold at half speed while moving toward a limit would need more room than is left: the check sees the hold's
    own brake (not the extrema of the plan before it) and brakes at the full limits, never commanding a jump."""
    lo, hi = np.array([-0.5]), np.array([0.5])
    amax = 4.0
    sh = Shaper(np.array([1.0]), np.array([amax]), dt=0.002, lo=lo, hi=hi)
    sh.reset(np.array([0.1]))
    while sh.q[0] > -0.28:  # a full-speed move to just above the lower limit, in its cruise
        sh.step(np.array([-0.499]))
    assert sh.v[0] < -0.9
    q = [sh.q[0]]
    for _ in range(400):
        sh.step(np.array([np.nan]), speed=0.5)  # hold at half the limits: its brake would pass -0.5
        q.append(sh.q[0])
    q = np.array(q)
    assert sh.fallbacks >= 1 and np.all(q >= lo[0])
    acc = np.diff(q, 2) / sh.dt**2
    assert np.abs(acc).max() <= amax * 1.05  # stopped by the plan, not by a clip at the limit


def test_profile_extrema_match_the_sampled_trajectory() -> None:
    """The exact extrema of ruckig profiles (position and velocity interface, moving and accelerating starts, brake
    pre-profiles from states beyond the limits) against the trajectory sampled densely."""
    from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, Synchronization

    from runtime.shaper import profile_extrema

    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(300):
        otg, inp, out = Ruckig(1, 0.002), InputParameter(1), OutputParameter(1)
        inp.synchronization = Synchronization.No
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = [1.0], [4.0], [200.0]
        inp.current_position = [rng.uniform(-0.5, 0.5)]
        inp.current_velocity = [rng.uniform(-1.3, 1.3)]  # beyond the velocity limit at times: a brake pre-profile
        inp.current_acceleration = [rng.uniform(-5.0, 5.0)]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [rng.uniform(-0.5, 0.5)], [0.0], [0.0]
        if rng.random() < 0.5:
            inp.per_dof_control_interface = [ControlInterface.Velocity]
        if otg.update(inp, out) not in (Result.Working, Result.Finished):
            continue
        traj = out.trajectory
        x = np.array([traj.at_time(t)[0][0] for t in np.linspace(0.0, traj.duration, 4001)])
        lo, hi = profile_extrema(traj.profiles[0][0])
        step = 1.3 * traj.duration / 4000  # the sampling can miss an extremum by up to a step's travel
        assert x.min() - step <= lo <= x.min() + 1e-12 and x.max() - 1e-12 <= hi <= x.max() + step
        checked += 1
    assert checked > 250
