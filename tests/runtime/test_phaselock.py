"""The phase lock slides a simulated loop's deadlines to just after a steady stream's arrivals, in bounded steps,
and leaves the loop alone for arrivals without a steady phase."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.phaselock import PhaseLock

P = 0.004


def simulate(arrivals: np.ndarray, lock: PhaseLock, cycles: int) -> tuple[list[float], list[float]]:
    """Run a loop of ``cycles`` deadlines against sorted arrival times; returns (per-arrival wait to its cycle,
    per-cycle corrections)."""
    deadline, i = P, 0
    waits, steps = [], []
    for _ in range(cycles):
        while i < len(arrivals) and arrivals[i] <= deadline:
            lock.arrival(arrivals[i], deadline)
            waits.append(deadline - arrivals[i])
            i += 1
        step = lock.correction()
        steps.append(step)
        deadline += P + step
    return waits, steps


@pytest.mark.parametrize("phase", [0.1, 0.37, 0.5, 0.81, 0.99])
def test_locks_onto_a_steady_stream_at_any_phase(phase: float) -> None:
    rng = np.random.default_rng(3)
    arrivals = (np.arange(2000) + phase) * P + rng.normal(0, 30e-6, 2000)  # 30 µs arrival jitter
    lock = PhaseLock(P)
    waits, steps = simulate(np.sort(arrivals), lock, 2000)
    assert lock.locked
    tail = np.array(waits[-500:])
    assert abs(np.median(tail) - lock.lead) < 50e-6  # cycles now fall one lead after the frames
    assert np.percentile(tail, 99) < lock.lead + 150e-6
    assert max(abs(s) for s in steps) <= lock.max_step * P + 1e-15  # never more than a few % of a period


def test_follows_a_producer_whose_clock_drifts() -> None:
    drift = 1 + 200e-6  # 200 ppm slower producer
    arrivals = (np.arange(3000) + 0.3) * P * drift
    lock = PhaseLock(P)
    waits, _ = simulate(arrivals, lock, 3000)
    assert abs(np.median(waits[-500:]) - lock.lead) < 50e-6


def test_incoherent_arrivals_leave_the_loop_alone() -> None:
    rng = np.random.default_rng(4)
    arrivals = np.sort(rng.uniform(0, 2000 * P, 2000))  # no steady phase
    lock = PhaseLock(P)
    _, steps = simulate(arrivals, lock, 2000)
    assert not lock.locked
    assert sum(abs(s) for s in steps) < 5 * P * lock.max_step  # at most a few stray steps early on


def test_a_stream_at_a_rate_that_does_not_divide_the_loop_is_not_chased() -> None:
    arrivals = (np.arange(800) + 0.2) * 2.5 * P  # 100 Hz against a 250 Hz loop: phases alternate half a period
    lock = PhaseLock(P)
    _, steps = simulate(arrivals, lock, 2000)
    assert not lock.locked
    assert all(s == 0.0 for s in steps)


def test_half_rate_stream_locks_every_other_cycle() -> None:
    arrivals = (np.arange(1000) + 0.6) * 2 * P  # 125 Hz: every other cycle takes a frame
    lock = PhaseLock(P)
    waits, _ = simulate(arrivals, lock, 2000)
    assert lock.locked
    assert abs(np.median(waits[-200:]) - lock.lead) < 50e-6


class _Pipe:
    """A command pipe holding given commands (what :meth:`runtime.runner.Runner._drain` reads)."""

    def __init__(self, cmds: list) -> None:
        self.cmds = cmds

    def recv(self, most: int) -> list:
        out, self.cmds = self.cmds[:most], self.cmds[most:]
        return out


def test_runner_feeds_the_lock_the_daemons_receipt_stamps() -> None:
    """The loop takes a frame off the pipe either at once or only at the next cycle's start (it does not watch the
    pipe during a cycle's work nor just before a cycle): the lock must judge the frame by when the daemon received
    it, which that does not move, or a steady 500 Hz sender's phases split in two clusters and it never locks."""
    from runtime.core.commands import Live
    from runtime.runner import Runner

    period, lead = 0.002, 0.0006
    runner = Runner.__new__(Runner)  # only what _drain touches
    runner.phase_lock = PhaseLock(period, lead=lead)
    from runtime.input_trace import InputTrace

    runner.trace = InputTrace()
    rng = np.random.default_rng(5)
    deadline = 1.0
    for k in range(400):
        received = deadline - lead + rng.normal(0, 20e-6)  # a steady sender at the lock's set point
        taken = received + 80e-6 if k % 2 else deadline  # at once, or at the cycle's start (the blind window)
        runner.clock = lambda taken=taken: taken
        runner.commands = _Pipe([Live(k, received=received)])
        runner._drain(deadline)
        assert runner.phase_lock.last_error == pytest.approx(deadline - received - lead)
        deadline += period + runner.phase_lock.correction()
    assert runner.phase_lock.locked
    assert runner.trace.count == 400 and np.isfinite(runner.trace.last(1)[0][0])


def test_a_steady_stream_with_late_stragglers_stays_locked() -> None:
    """At 500 Hz a loaded host delivers some frames milliseconds late: the lock, once engaged, holds through them
    (it lets go only when the phases really scatter) and a straggler (here a third to two thirds of a period late:
    later ones look like the next frame on time) moves no deadline."""
    p = 0.002
    rng = np.random.default_rng(11)
    n = 6000
    late = rng.random(n) < 0.12
    arrivals = (np.arange(n) + 0.37) * p + rng.normal(0, 40e-6, n) + late * rng.uniform(0.6e-3, 1.4e-3, n)
    lock = PhaseLock(p, lead=0.0006)
    deadline, i, locked, waits, moved_by_late = p, 0, [], [], []
    order = np.argsort(arrivals)
    arrivals, late = arrivals[order], late[order]
    for _ in range(n):
        taken_late = False
        while i < n and arrivals[i] <= deadline:
            lock.arrival(arrivals[i], deadline)
            if not late[i]:
                waits.append(deadline - arrivals[i])
            taken_late = bool(late[i])
            i += 1
        step = lock.correction()
        if taken_late:
            moved_by_late.append(step)
        locked.append(lock.locked)
        deadline += p + step
    assert all(locked[1000:]), f"let go {locked[1000:].count(False)} times"
    assert abs(np.median(waits[-1000:]) - lock.lead) < 60e-6
    assert max(abs(s) for s in moved_by_late[-200:]) < 0.25 * lock.max_step * p  # stragglers move nothing much


def test_a_stream_that_moves_its_phase_is_locked_again() -> None:
    """Every frame a straggler (the sender re-phased by half a period): the lock lets go and locks onto the new
    phase."""
    p = 0.002
    n = 4000
    arrivals = (np.arange(n) + 0.3) * p
    arrivals[n // 2:] += 0.5 * p
    lock = PhaseLock(p, lead=0.0006)
    waits, _ = simulate_p(np.sort(arrivals), lock, n, p)
    assert lock.locked
    assert abs(np.median(waits[-300:]) - lock.lead) < 60e-6


def simulate_p(arrivals: np.ndarray, lock: PhaseLock, cycles: int, period: float) -> tuple[list[float], list[float]]:
    """:func:`simulate` at another period."""
    deadline, i = period, 0
    waits, steps = [], []
    for _ in range(cycles):
        while i < len(arrivals) and arrivals[i] <= deadline:
            lock.arrival(arrivals[i], deadline)
            waits.append(deadline - arrivals[i])
            i += 1
        step = lock.correction()
        steps.append(step)
        deadline += period + step
    return waits, steps


def simulate_slotted(arrivals: np.ndarray, lock: PhaseLock, hop: float, period: float = P) -> list[float]:
    """A loop with wake on input (:class:`runtime.runner.Runner`): a frame taken ``hop`` after it arrived runs the
    cycle at once if its period slot (the period before the next deadline) has begun, else at the slot's start; that
    cycle serves the deadline, and the next is a period later. With no frame in a slot, the cycle runs at its
    deadline. Returns each frame's wait from being taken to its cycle."""
    deadline, waits = 2 * period, []
    for a in arrivals:
        taken = a + hop
        while taken >= deadline:  # slots with no frame: their deadline's own cycle
            deadline += period + lock.correction()
        lock.arrival(a, deadline)
        waits.append(max(taken, deadline - period) - taken)
        deadline += period + lock.correction()
    return waits


@pytest.mark.parametrize("phase", [0.05, 0.3, 0.55, 0.8, 0.95])
def test_with_wake_on_input_frames_run_their_cycle_when_taken(phase: float) -> None:
    """With wake on input the loop runs a frame's cycle as soon as it is taken, once its slot began. The lock must
    centre the frames in their slots: folded modulo the period, its error is also zero with every slot starting
    half a period after the frames, which then all wait that long (where the folded lock settles here)."""
    from runtime.runner import phase_lock

    rng = np.random.default_rng(7)
    arrivals = np.sort((np.arange(3000) + phase) * P + rng.normal(0, 30e-6, 3000))
    lock = phase_lock(P, 0.0006, wake_on_input=True)
    waits = simulate_slotted(arrivals, lock, hop=200e-6)
    assert lock.locked and lock.slotted
    assert np.percentile(waits[-500:], 99) < 1e-6  # every frame runs its cycle the moment it is taken
    folded_waits = simulate_slotted(arrivals, PhaseLock(P, lead=0.5 * P), hop=200e-6)
    assert np.median(folded_waits[-500:]) > 0.4 * P  # the other equilibrium: every frame waits for its slot


def test_without_wake_on_input_the_lock_keeps_its_lead() -> None:
    from runtime.runner import phase_lock

    lock = phase_lock(P, 0.0006, wake_on_input=False)
    assert lock.lead == 0.0006 and not lock.slotted
