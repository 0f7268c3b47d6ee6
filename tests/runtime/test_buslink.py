"""Bus processes: each bus of the sample head in its own process, driving emulators that run in child processes.

Measured positions come back through the real drivers (CiA 402 over socketcand, Dynamixel over a pseudo-terminal);
ground truth comes from the emulator processes over their control channel. Waits poll feedback with generous
deadlines (the machine may be loaded); nothing here is timed.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.base import LifecycleState
from drivers.errors import BusInitError, ConfigError
from models.headspec import HeadSpec, load_head
from runtime.bus import BusFeedback, BusProxy
from runtime.hardware import Hardware, motor_config
from tests._wait import wait_until

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"
DEG = math.pi / 180


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie is not running; its parent just has not reaped it yet
        return f.read().rsplit(")", 1)[1].split()[0] != "Z"


def _ramp(hw: Hardware, goals: dict[str, float], duration: float = 0.4) -> None:
    """Post a smooth ramp from the measured positions to ``goals`` on every bus, as a control loop would."""
    start = {bus: link.feedback().positions.copy() for bus, link in hw.proxies.items()}
    end = {bus: s.copy() for bus, s in start.items()}
    for name, value in goals.items():
        bus = hw.bus_of(name)
        end[bus][hw.proxies[bus].actuators.index(name)] = value
    t0 = time.monotonic()
    while True:
        s = min((time.monotonic() - t0) / duration, 1.0)
        s = s * s * (3 - 2 * s)
        for bus, link in hw.proxies.items():
            link.post(start[bus] + (end[bus] - start[bus]) * s)
        if s >= 1.0:
            return
        time.sleep(0.004)


@pytest.fixture(scope="module")
def head() -> HeadSpec:
    return load_head(SAMPLE)


@pytest.fixture(scope="module")
def hw(head: HeadSpec) -> Iterator[Hardware]:
    """The sample head's two buses in bus processes, their emulators in child processes; left inactive, no faults."""
    linked = Hardware.from_head(head)
    try:
        linked.start()
        yield linked
    finally:
        linked.stop()


def test_posted_targets_reach_the_motors_and_feedback_follows(hw: Hardware) -> None:
    fb = hw.feedback()
    assert {b: f.state for b, f in fb.items()} == {"can0": LifecycleState.INACTIVE, "dxl": LifecycleState.INACTIVE}
    assert all(f.connected and f.seq >= 1 and np.all(np.isfinite(f.positions)) for f in fb.values())
    seq0 = fb["dxl"].seq
    wait_until(lambda: hw.proxies["dxl"].feedback().seq > seq0 + 2, 30, "idle reads keep feedback fresh")

    hw.call("enable")
    assert all(f.state is LifecycleState.ACTIVE for f in hw.feedback().values())
    goals = {"jaw": 8 * DEG, "lip_corner_r_back": -6 * DEG, "brow_l": 7 * DEG, "lid_r": -5 * DEG}
    _ramp(hw, goals)
    posted = {bus: link.feedback() for bus, link in hw.proxies.items()}

    def arrived() -> bool:
        pos = hw.positions()
        return all(abs(pos[n] - v) < 0.3 * DEG for n, v in goals.items())

    wait_until(arrived, 30, "measured positions reach the posted targets")
    truth = hw.simulated_positions()
    pos = hw.positions()
    for name, value in goals.items():
        assert truth[name] == pytest.approx(value, abs=0.5 * DEG), name  # the emulator agrees with the driver
        assert pos[name] == pytest.approx(truth[name], abs=0.3 * DEG), name
    for bus, link in hw.proxies.items():
        f = link.feedback()
        assert f.write_stamp > 0 and f.io_us > 0 and f.stamp > 0
        for name, value in goals.items():
            if name in link.actuators:
                assert f.written[link.actuators.index(name)] == pytest.approx(value), name
        wait_until(lambda b=bus: hw.proxies[b].feedback().seq > posted[b].seq, 30,
                   f"{bus}: feedback keeps coming after the targets")
    hw.call("disable")
    assert all(f.state is LifecycleState.INACTIVE for f in hw.feedback().values())
    # inactive: posted targets are not written
    before = hw.proxies["dxl"].feedback()
    hw.post("dxl", before.positions + 3 * DEG)
    wait_until(lambda: hw.proxies["dxl"].feedback().seq > before.seq + 2, 30, "another read")
    after = hw.proxies["dxl"].feedback()
    assert after.write_stamp == before.write_stamp
    assert np.allclose(after.positions, before.positions, atol=0.3 * DEG)


def test_targets_posted_before_enable_are_never_written(hw: Hardware) -> None:
    link = hw.proxies["dxl"]
    fb = link.feedback()
    link.post(fb.positions + 20 * DEG)  # stale: posted while inactive
    link.call("enable")
    try:
        time.sleep(0.1)
        after = link.feedback()
        assert after.state is LifecycleState.ACTIVE and after.write_stamp == fb.write_stamp
        assert np.allclose(after.positions, fb.positions, atol=0.3 * DEG)
    finally:
        link.call("disable")


def test_canopen_heartbeat_loss_faults_the_bus_naming_the_drive_and_reset_recovers(hw: Hardware) -> None:
    link = hw.proxies["can0"]
    hw.call("enable")
    hold = link.feedback().positions.copy()
    hw.emulator("can0").inject("stop_heartbeat", device=3)
    t0 = time.monotonic()
    while link.feedback().state is not LifecycleState.FAULT and time.monotonic() - t0 < 10:
        link.post(hold)  # the loop keeps posting: posts stay accepted while the bus faults
        time.sleep(0.004)
    fb = link.feedback()
    assert fb.state is LifecycleState.FAULT
    assert "lip_corner_l_back" in fb.faults, fb.faults
    assert hw.proxies["dxl"].feedback().state is LifecycleState.ACTIVE  # the other bus is unaffected
    hw.emulator("can0").inject("resume_heartbeat", device=3)
    hw.call("disable")  # dxl: active -> inactive; can0 is in fault and stays there
    assert link.feedback().state is LifecycleState.FAULT
    link.call("reset")
    fb = link.feedback()
    assert fb.state is LifecycleState.INACTIVE and fb.faults == {} and fb.connected


def test_dynamixel_overheat_faults_the_bus_naming_the_servo_and_reset_recovers(hw: Hardware) -> None:
    link = hw.proxies["dxl"]
    link.call("enable")
    hw.emulator("dxl").inject("overheat", device=3)
    wait_until(lambda: link.feedback().state is LifecycleState.FAULT, 30, "overheat fault")
    fb = link.feedback()
    assert fb.faults["brow_l"][0] & 0x04, fb.faults  # overheating bit of Hardware Error Status
    assert hw.faults()["dxl/brow_l"] == fb.faults["brow_l"]
    assert link.feedback().faults is fb.faults  # unchanged faults are not rebuilt per call
    ticket = link.request("enable")
    wait_until(lambda: link.result(ticket) is not None, 30, "enable refused")
    hw.emulator("dxl").clear()
    link.call("reset")
    wait_until(lambda: link.feedback().faults == {}, 30, "fault cleared")
    assert link.feedback().state is LifecycleState.INACTIVE


def test_bad_requests_and_targets_are_refused(hw: Hardware) -> None:
    link = hw.proxies["can0"]
    with pytest.raises(ValueError, match="unknown operation 'arm'"):
        link.request("arm")
    with pytest.raises(ValueError, match="3 targets for 7 actuators"):
        link.post(np.zeros(3))
    ticket = link.request("enable")
    wait_until(lambda: link.result(ticket) is not None, 30, "enable")
    link.post(link.feedback().positions + 40 * DEG)  # beyond the jaw's limit: the driver's check refuses it
    wait_until(lambda: link.feedback().state is LifecycleState.FAULT, 30, "a refused target faults the bus")
    assert "CommandRejected: jaw: target" in link.feedback().faults["can0"][1]
    link.call("reset")
    assert link.feedback().state is LifecycleState.INACTIVE


def _single_link(head: HeadSpec, bus: str) -> tuple[BusProxy, object]:
    from runtime import simhw

    acts = head.actuators_on(bus)
    motors = [motor_config(a) for a in acts]
    sim = simhw.start(head.buses[bus].driver, bus, head.buses[bus].driver_options(), motors,
                      {a.name: a.neutral for a in acts})
    link = BusProxy(head.buses[bus].driver, bus, sim.options, motors, open_attempts=3)
    try:
        link.start(60)
    except BaseException:
        sim.close()
        raise
    return link, sim


def test_a_dead_emulator_faults_the_bus_and_the_loop_side_keeps_going(head: HeadSpec) -> None:
    link, sim = _single_link(head, "dxl")
    try:
        link.call("enable")
        hold = link.feedback().positions.copy()
        sim.kill()
        t0 = time.monotonic()
        while link.feedback().state is not LifecycleState.FAULT and time.monotonic() - t0 < 15:
            link.post(hold)  # the loop side goes on posting and reading while the bus process meets a dead device
            time.sleep(0.002)
        fb = link.feedback()
        assert fb.state is LifecycleState.FAULT, fb
        assert not fb.connected or fb.faults, fb
        assert _alive(link.pid)  # the driver's errors did not kill the bus process
        published = link.feedback_published  # feedback publications: the bus process keeps publishing at the idle rate
        wait_until(lambda: link.feedback_published > published + 2, 30, "feedback still published")
        for _ in range(20):
            link.post(hold)
            assert link.feedback().state is LifecycleState.FAULT
    finally:
        pid = link.pid
        link.stop()
        sim.close()
    assert pid is not None and not _alive(pid) and not sim.alive
    link.stop()  # idempotent


def test_a_dead_bus_process_is_noticed_and_stop_leaves_no_process(head: HeadSpec) -> None:
    link, sim = _single_link(head, "can0")
    try:
        assert link.feedback().connected
        pid = link.pid
        assert pid is not None
        link.kill()
        fb = link.feedback()
        assert isinstance(fb, BusFeedback) and not fb.connected and fb.state is LifecycleState.FAULT
        assert "bus process exited" in fb.faults["can0"][1]
        ticket = link.request("reset")
        assert link.result(ticket) == (False, "bus 'can0': bus process is not running")
    finally:
        link.stop()
        sim.close()
    assert not _alive(pid) and not sim.alive


def test_an_unreachable_bus_raises_the_drivers_typed_error(head: HeadSpec, tmp_path: Path) -> None:
    acts = head.actuators_on("dxl")
    options = dict(head.buses["dxl"].options, port=str(tmp_path / "no-such-port"))
    link = BusProxy("dynamixel", "dxl", options, [motor_config(a) for a in acts])
    with pytest.raises(BusInitError, match="no-such-port"):
        link.start(60)
    assert link.pid is None
    link.stop()


def test_bus_and_emulator_processes_die_with_a_killed_parent() -> None:
    """A daemon killed with SIGKILL leaves no bus process or emulator behind."""
    import signal
    import subprocess
    import sys

    code = (  # the CAN bus only: the point is the process tree, and one bus starts fastest
        "import sys, time, tomllib\n"
        "from models.headspec import head_from_dict\n"
        "from runtime.hardware import Hardware\n"
        "data = tomllib.loads(open(sys.argv[1]).read())\n"
        "data['buses'] = {'can0': data['buses']['can0']}\n"
        "data['actuators'] = [a for a in data['actuators'] if a['bus'] == 'can0']\n"
        "data['links'] = {}\n"
        "data.pop('groups', None)\n"
        "hw = Hardware.from_head(head_from_dict(data, source=sys.argv[1]))\n"
        "hw.start()\n"
        "print(' '.join(str(p) for b in hw.proxies for p in (hw.proxies[b].pid, hw.emulator(b).pid)), flush=True)\n"
        "time.sleep(120)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(SAMPLE.parents[2]))
    proc = subprocess.Popen([sys.executable, "-c", code, str(SAMPLE)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout is not None
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    wait_until(lambda: not any(_alive(p) for p in pids), 30, "children gone after the parent's SIGKILL")


@pytest.mark.parametrize("bus", ["can0", "dxl"])
def test_emulator_processes_start_at_the_given_pose_and_report_ground_truth(head: HeadSpec, bus: str) -> None:
    from runtime import simhw

    acts = head.actuators_on(bus)
    motors = [motor_config(a) for a in acts]
    initial = {a.name: (3 + i) * DEG for i, a in enumerate(acts)}
    sim = simhw.start(head.buses[bus].driver, bus, head.buses[bus].driver_options(), motors, initial)
    try:
        assert sim.alive
        counts = sim.positions_counts()
        assert counts == pytest.approx({m.device_id: m.to_counts(initial[m.name]) for m in motors}, abs=1.0)
        with pytest.raises(RuntimeError, match="unknown fault"):
            sim.inject("melt", device=motors[0].device_id)
    finally:
        sim.close()
    assert not sim.alive
    with pytest.raises(ConfigError, match="no emulator for driver 'ethercat'"):
        simhw.start("ethercat", bus, {}, motors)


def test_transport_errors_count_as_a_lost_connection() -> None:
    """pyserial raises ``termios.error`` (not an OSError) when a pseudo-terminal vanishes under it; a missed answer
    is not a lost connection."""
    import termios

    from drivers.errors import BusTimeout
    from runtime.bus.process import _connection_lost

    assert _connection_lost(termios.error(5, "Input/output error"))
    assert _connection_lost(OSError(5, "Input/output error"))
    assert not _connection_lost(BusTimeout("brow_l", "no status packet"))
