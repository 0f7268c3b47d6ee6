"""Wake on input: a live value between deadlines runs the cycle at once, one cycle per period slot at most, with the
shaper advancing only by the time that passed; a run with early cycles replays bit for bit."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from runtime.core.shape import advance
from runtime.loop import RateScheduler
from runtime.runner import COMMAND_MARGIN_S
from runtime.shaper import Shaper
from tests._wait import wait_until
from tests.runtime.inputs.conftest import enable, show_head, started


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class _SteppingClock:
    """Moves 1 µs at each reading: the runner's margin logic meets the same instants however busy the machine is (a
    wall clock can pass the 300 µs margin while the test waits for a core)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        self.t += 1e-6
        return self.t


def test_an_idle_function_that_asks_ends_the_wait_early_and_serves_that_deadline() -> None:
    clock = _Clock()
    sched = RateScheduler(0.004, spin=0.0, clock=clock)
    deadline = sched.next

    def idle(until: float) -> bool:
        assert until == deadline
        clock.t = deadline - 0.003  # a value arrived three quarters of a period early
        return True

    late, missed = sched.wait(idle)
    assert sched.early and missed == 0 and abs(late + 0.003) < 1e-12
    assert sched.next == deadline + 0.004  # the early cycle took that deadline's place: next slot's deadline next

    def sleeper(until: float) -> None:
        clock.t = until

    late, missed = sched.wait(sleeper)
    assert not sched.early and late == 0.0 and abs(sched.next - (deadline + 0.008)) < 1e-12


def test_a_cycle_ahead_of_its_deadline_advances_the_shaper_by_the_time_that_passed() -> None:
    period = 0.004
    assert advance(period, 10.0, None) == period
    assert abs(advance(period, 10.0, 9.999) - 0.001) < 1e-12 and advance(period, 10.0, 9.99) == period
    assert advance(period, 10.0 + period, 10.0) == period  # late: no catching up
    vmax = np.array([1.0, 2.0])
    full = Shaper(vmax, np.array([1e3, 1e3]), np.array([1e7, 1e7]), dt=period)
    short = Shaper(vmax, np.array([1e3, 1e3]), np.array([1e7, 1e7]), dt=period)
    far = np.array([0.5, -0.5])
    for _ in range(20):  # up to speed toward a far target
        full.step(far)
        short.step(far)
    q0 = short.q.copy()
    q_full = full.step(far).copy()
    q_short = short.step(far, dt=period / 4).copy()
    assert np.all(np.abs(q_short - q0) <= vmax * period / 4 * (1 + 1e-9))  # the limits hold in real time
    assert np.allclose(np.abs(q_full - q0), vmax * period) and np.allclose(np.abs(q_short - q0), vmax * period / 4)
    short.step(far)  # and the next cycle advances a whole period again
    assert np.allclose(np.abs(short.q - q_short), vmax * period)


FRAGMENT = """
[inputs.osc]
bind = "127.0.0.1:0"
watchdog = false
[inputs.osc.map]
"/face/jaw" = "jaw"
"""


def test_an_osc_value_between_deadlines_is_written_by_an_early_cycle_that_replays_bit_for_bit(tmp_path: Path) -> None:
    """OSC values sent at random phases of a 250 Hz loop: cycles run ahead of their deadlines carry them (full
    cycles whose time is off the deadline grid, none closer than a quarter period to the one before), the head
    stays active (the drivers' rate guard accepted every write), and the recorded inputs replay bit for bit."""
    from pythonosc.udp_client import SimpleUDPClient

    from models.client import Client
    from models.headspec import load_head
    from runtime.core import core as K
    from runtime.core.commands import Live
    from runtime.core.state import CoreState
    from runtime.daemon import Daemon
    from tests.runtime.conftest import daemon_overrides

    head = load_head(show_head(tmp_path, FRAGMENT))
    overrides = daemon_overrides(tmp_path, **{"runtime.rate_hz": 250.0, "safety.feedback_timeout_s": 5.0})
    d = started(lambda: Daemon(head, overrides, target_solvers=(), record_inputs=True))
    rng = np.random.default_rng(3)
    try:
        with Client(d.command_endpoint, timeout=30) as c:
            enable(c)
            host, port = c.call("hello")["inputs"]["osc"]["udp"].rsplit(":", 1)
            osc = SimpleUDPClient(host, int(port))
            for k in range(12):
                time.sleep(0.03 + rng.uniform(0.0, d.period))
                osc.send_message("/face/jaw", 2.0 + (k % 3))
            assert wait_until(lambda: c.call("status")["loop"].get("early", 0) > 0, 10, "an early cycle")
            assert c.call("status")["lifecycle"] == "active"
    finally:
        d.stop()
    inputs, writes = d.input_log, d.runner.output_log
    assert inputs is not None and writes is not None
    full = [i for i in inputs if not i.between_cycles]
    t = np.array([i.t for i in full])
    assert np.all(np.diff(t) >= 0.25 * d.period - 1e-9)  # none closer than a quarter period to the one before
    grid = np.abs(((t - t[0]) / d.period + 0.5) % 1.0 - 0.5) * d.period
    early = [i for i, off in zip(full, grid, strict=True) if off > 50e-6 and any(isinstance(c, Live)
                                                                                   for c in i.commands)]
    assert early, "no full cycle off the deadline grid carried an OSC value"
    fresh = CoreState.initial(head, d.params, [])
    for k, inp in enumerate(inputs):
        out = K.step(fresh, d.params, inp)
        if writes[k] is None:
            assert out.write is None, k
        else:
            assert out.write is not None and out.write.tobytes() == writes[k].tobytes(), k


def _margin_runner(tmp_path: Path):
    """A runner over the sample head's core (active, ideal buses) reading a real command pipe, between two cycles."""
    from runtime import ipc
    from runtime.core import commands as C
    from runtime.runner import Runner
    from tests.runtime.test_core import Rig

    rig = Rig(250.0)
    rig.call(C.Enable)
    path = str(tmp_path / "commands")
    ipc.make_pipe(path)
    reader = ipc.PipeReader(path)
    writer = ipc.PipeWriter(path)
    clock = _SteppingClock()
    runner = Runner(rig.params, rig.state, [], None, reader, ipc.EStopFlag(), clock=clock, input_log=[])
    return rig, runner, reader, writer, clock


def test_a_value_in_the_margin_before_a_deadline_runs_that_cycle_at_once(tmp_path: Path) -> None:
    """In the last ``COMMAND_MARGIN_S`` before a cycle the loop steps no commands between cycles; a live value that
    arrives there is taken for that cycle and runs it at once, instead of waiting out the margin and the spin."""
    from runtime.core import commands as C

    rig, runner, reader, writer, clock = _margin_runner(tmp_path)
    jaw = rig.channels.indices(("jaw",))
    try:
        assert rig.state.life.commanding and runner.wake_on_input
        now = clock.t
        until = now + 0.9 * COMMAND_MARGIN_S  # inside the margin: no commands taken between cycles
        runner._deadline, runner._last_t = until + 200e-6, now - 0.004
        writer.send(C.Live(7, channels=jaw, values=np.array([3.0]), received=now))
        assert runner._idle(until) is True  # the cycle now (without the margin wake: False, at ``until``)
        assert [type(c) for c in runner._carry] == [C.Live]  # the cycle takes it
        assert runner.input_log == []  # and nothing was stepped between cycles
        runner._carry = []
        # a command that moves nothing waits for the cycle in the margin, as before
        now = clock.t
        until = now + 0.5 * COMMAND_MARGIN_S
        runner._deadline, runner._last_t = until + 200e-6, now - 0.004
        writer.send(C.Status(8))
        assert runner._idle(until) is False
        assert clock.t >= until
        assert [type(c) for c in runner._carry] == [C.Status] and runner.input_log == []
    finally:
        writer.close()
        reader.close()
        runner.estop.close()
