"""Wake on input: a live value between deadlines runs the cycle at once, one cycle per period slot at most, with the
shaper advancing only by the time that passed; a run with early cycles replays bit for bit."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from runtime.core.shape import advance
from runtime.loop import RateScheduler
from runtime.shaper import Shaper
from tests._wait import wait_until
from tests.runtime.inputs.conftest import enable, show_head, started


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
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
