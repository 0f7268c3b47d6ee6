"""``canopen402`` driver back to back with the emulated CiA 402 drives (python-can virtual bus, socketcand)."""

from __future__ import annotations

import math
import statistics
import time
import uuid
from pathlib import Path

import pytest

from drivers.base import LifecycleState, MotorConfig
from drivers.canopen402 import (
    FAULT_FEEDBACK_STALE,
    FAULT_HEARTBEAT_LOST,
    FAULT_NODE_STATE,
    CanOpen402Bus,
)
from drivers.errors import BusInitError, BusTimeout, CommandRejected, ConfigError, DeviceFault, LifecycleError
from drivers.registry import create_bus
from sim_hardware.canopen import drive as drv
from sim_hardware.canopen.network import DriveSet
from sim_hardware.socketcand import SocketcandServer
from tests._wait import wait_until

MOTORS = (
    MotorConfig.rotary("jaw", 1, counts_per_rev=4096, gear_ratio=10.0, min_position=-1.0, max_position=1.0,
                       max_velocity=2.0),
    MotorConfig.rotary("lip", 2, counts_per_rev=4096, gear_ratio=5.0, direction=-1, min_position=-1.0,
                       max_position=1.0, max_velocity=2.0),
)


@pytest.fixture
def drives():
    channel = f"test-co402-{uuid.uuid4().hex[:10]}"
    ds = DriveSet([1, 2], channel=channel, seed=7, initial_positions={1: 1000.0, 2: -500.0}).start()
    yield ds
    ds.stop()


#: Timeouts that an emulator thread stalled by a loaded host does not trip (the driver's defaults are for real drives);
#: a test about one of them sets it.
PATIENT = {"heartbeat_timeout_s": 1.0, "feedback_timeout_s": 1.0, "sdo_timeout_s": 2.0, "state_timeout_s": 2.0}


def _bus(drives: DriveSet, motors=MOTORS, **options) -> CanOpen402Bus:
    """The driver on the drives' channel, patient except where the test sets a timeout."""
    opts = {"interface": "virtual", "channel": drives.channel, **PATIENT, **options}
    return CanOpen402Bus("can0", opts, motors)


@pytest.fixture
def bus(drives):
    b = _bus(drives)
    yield b
    b.close()


@pytest.fixture
def bus_100ms(drives):
    """The driver with a 0.1 s heartbeat timeout, for the test that times it."""
    b = _bus(drives, heartbeat_timeout_s=0.1)
    yield b
    b.close()


def _run(bus: CanOpen402Bus, seconds: float, target, period: float = 0.005) -> dict:
    """Cyclic read → write at about 1/period Hz; returns the last read."""
    start = time.monotonic()
    states = bus.read()
    while (t := time.monotonic() - start) < seconds:
        states = bus.read()
        bus.write({m.name: target(m, t) for m in MOTORS})
        time.sleep(period)
    return states


def _cycle_until(bus: CanOpen402Bus, predicate, timeout: float = 10.0) -> bool:
    """Keep reading (the runtime does) until ``predicate()`` or timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        bus.read()
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def _reset_accepted(bus: CanOpen402Bus) -> bool:
    """Reset the fault; False (nothing changed) while a node's heartbeat is still missing."""
    try:
        bus.reset_fault()
    except BusTimeout:
        return False
    return True


def test_open_enable_write_read_tracks_and_disable(bus, drives):
    bus.open()
    assert bus.state is LifecycleState.INACTIVE
    assert all(d.nmt_state == "OPERATIONAL" for d in drives.drives.values())
    first = bus.read()
    assert first["jaw"].position == pytest.approx(MOTORS[0].from_counts(1000), abs=1e-3)
    assert first["lip"].position == pytest.approx(MOTORS[1].from_counts(-500), abs=1e-3)
    assert not first["jaw"].enabled
    bus.enable()
    assert all(d.state == drv.OPERATION_ENABLED for d in drives.drives.values())
    # Enable holds the present position: nothing jumped.
    assert drives.drives[1].position_counts == pytest.approx(1000, abs=5)

    start = {m.name: first[m.name].position for m in MOTORS}
    states = _run(bus, 0.8, lambda m, t: start[m.name] + 0.4 * min(t / 0.6, 1.0))
    states = _run(bus, 0.15, lambda m, t: start[m.name] + 0.4)
    for motor in MOTORS:
        goal = start[motor.name] + 0.4
        assert states[motor.name].position == pytest.approx(goal, abs=2e-3)
        truth = motor.from_counts(drives.drives[motor.device_id].position_counts)
        assert truth == pytest.approx(goal, abs=2e-3)
        assert states[motor.name].enabled and states[motor.name].fault_code == 0
    # Direction -1 on the lip: output moved +0.4 rad, so the encoder count went down.
    assert drives.drives[2].position_counts < -500 - 1000
    assert bus.diagnostics()["syncs"] > 50

    bus.disable()
    assert bus.state is LifecycleState.INACTIVE
    assert all(d.state == drv.SWITCHED_ON for d in drives.drives.values())
    with pytest.raises(LifecycleError):
        bus.write({"jaw": 0.0})
    assert not bus.read()["jaw"].enabled


def test_velocity_is_reported_in_si(bus, drives):
    bus.open()
    bus.enable()
    start = {m.name: bus.read()[m.name].position for m in MOTORS}
    t0 = time.monotonic()
    samples: dict[str, list[float]] = {m.name: [] for m in MOTORS}
    while (t := time.monotonic() - t0) < 0.5:  # 1 rad/s ramp on both (the lip's encoder counts down)
        states = bus.read()
        if t > 0.2:
            for name, state in states.items():
                samples[name].append(state.velocity)
        bus.write({m.name: start[m.name] + 1.0 * t for m in MOTORS})
        time.sleep(0.005)
    for name, values in samples.items():
        # Median: robust to the catch-up spikes after a scheduling stall of this thread on a busy machine.
        assert statistics.median(values) == pytest.approx(1.0, abs=0.15), name
    assert math.isfinite(states["jaw"].effort)


def test_tpdo2_on_every_nth_sync_still_reports_velocity(drives):
    """``tpdo2_every = 5``: the drives' TPDO2 transmission type is 5, a listener on the bus sees one TPDO2 per drive
    for every five SYNCs (TPDO1 on each), and the velocity it carries is still right."""
    import can

    bus = _bus(drives, tpdo2_every=5)
    listener = can.Bus(interface="virtual", channel=drives.channel, receive_own_messages=False)
    try:
        bus.open()
        assert all(d._get(0x1801, 2) == 5 and d._get(0x1800, 2) == 1 for d in drives.drives.values())
        bus.enable()
        start = bus.read()["jaw"].position
        while listener.recv(0.0) is not None:  # what went before the count
            pass
        counts = {0x80: 0, 0x181: 0, 0x281: 0}
        velocities, t0 = [], time.monotonic()
        while (t := time.monotonic() - t0) < 0.6:  # 1 rad/s ramp
            states = bus.read()
            if t > 0.25:
                velocities.append(states["jaw"].velocity)
            bus.write({"jaw": start + 1.0 * t})
            while (msg := listener.recv(0.0)) is not None:
                if msg.arbitration_id in counts:
                    counts[msg.arbitration_id] += 1
            time.sleep(0.004)
        assert counts[0x80] >= 50
        assert counts[0x181] >= 0.8 * counts[0x80]
        assert 0.12 <= counts[0x281] / counts[0x80] <= 0.28, counts
        assert statistics.median(velocities) == pytest.approx(1.0, abs=0.15)
    finally:
        listener.shutdown()
        bus.close()


def test_targets_computed_before_the_enable_hold_are_rated_on_the_time_since_it(bus, drives):
    """A caller stamps its targets when it computed them; the first one after enable may predate the hold enable set
    up (the caller had not seen it yet). Its step is rated on the time that has passed since that hold."""
    bus.open()
    t_before = time.monotonic()
    bus.enable()
    hold = bus.read()["jaw"].position
    time.sleep(0.05)
    with pytest.raises(CommandRejected, match="max_velocity"):  # far more than 2 rad/s over 50 ms
        bus.write({"jaw": hold + 0.5}, stamp=t_before)
    bus.write({"jaw": hold + 0.02}, stamp=t_before)  # 0.4 rad/s over the 50 ms since the hold: taken
    assert bus.state is LifecycleState.ACTIVE
    with pytest.raises(CommandRejected, match="max_velocity"):  # later targets: rated between their own stamps
        bus.write({"jaw": hold + 0.04}, stamp=t_before + 0.001)


def test_last_commands_after_enable_are_the_hold_the_next_step_is_rated_from(bus, drives):
    """After enable each motor holds where the driver read it; ``last_commands`` says where, and a controller that
    starts from there has a zero first step whenever it comes. A position measured later that moved on (a motor
    settling or still coasting) is a step from the hold, rated on the time between the stamps."""
    bus.open()
    bus.enable()
    held = bus.last_commands()
    t_hold = time.monotonic()
    assert held["jaw"] == pytest.approx(drives.drives[1].position_counts * 2 * math.pi / 40960, abs=1e-3)
    with pytest.raises(CommandRejected, match="max_velocity"):  # 0.05 rad one millisecond after the hold
        bus.write({"jaw": held["jaw"] + 0.05, "lip": held["lip"]}, stamp=t_hold + 0.001)
    bus.write(held, stamp=t_hold + 0.001)
    assert bus.state is LifecycleState.ACTIVE and bus.last_commands() == held


def test_limits_guard_rejects_and_sends_nothing(bus, drives):
    bus.open()
    bus.enable()
    before = drives.drives[1].position_counts
    with pytest.raises(CommandRejected, match="outside"):
        bus.write({"jaw": 1.5})
    with pytest.raises(CommandRejected, match="not finite"):
        bus.write({"jaw": math.nan})
    with pytest.raises(CommandRejected, match="max_velocity"):
        bus.write({"jaw": bus.read()["jaw"].position + 0.5})
    with pytest.raises(CommandRejected, match="unknown motor"):
        bus.write({"nose": 0.0})
    time.sleep(0.05)
    assert drives.drives[1].position_counts == pytest.approx(before, abs=2)
    assert bus.state is LifecycleState.ACTIVE


def test_heartbeat_loss_faults_within_timeout_and_quick_stops_everyone(bus_100ms, drives):
    bus = bus_100ms
    bus.open()
    bus.enable()
    _run(bus, 0.1, lambda m, t: bus.read()[m.name].position)
    drives.inject("stop_heartbeat", device=2)
    t0 = time.monotonic()
    wait_until(lambda: bus.state is LifecycleState.FAULT, 10.0, "the monitor thread's heartbeat fault")
    elapsed = time.monotonic() - t0
    # Not before the 0.1 s timeout (less the 25 ms heartbeat period already running), and promptly after it
    # (the bound is loose only for scheduling delays on a busy machine).
    assert 0.1 - 0.025 <= elapsed < 0.1 + 0.5
    code, message = bus.faults()["lip"]
    assert code == FAULT_HEARTBEAT_LOST and "node 2" in message
    with pytest.raises(DeviceFault) as err:
        bus.write({"jaw": 0.0})
    assert err.value.code == FAULT_HEARTBEAT_LOST
    # Safe state: every drive was quick-stopped and ended torque-off.
    assert _cycle_until(bus, lambda: all(d.state == drv.SWITCH_ON_DISABLED for d in drives.drives.values()))
    # No reset while the node is still silent.
    with pytest.raises(BusTimeout) as timeout:
        bus.reset_fault()
    assert timeout.value.device == "lip"
    drives.inject("resume_heartbeat", device=2)
    # The reset is refused until the driver has heard node 2's heartbeat again (it names the silent node).
    wait_until(lambda: _reset_accepted(bus), 10.0, "a fault reset accepted once node 2's heartbeat resumes")
    assert bus.state is LifecycleState.INACTIVE and bus.faults() == {}
    bus.enable()
    assert bus.state is LifecycleState.ACTIVE


def test_drive_fault_emcy_reports_its_code_then_recovers(bus, drives):
    bus.open()
    bus.enable()
    _run(bus, 0.05, lambda m, t: bus.read()[m.name].position)
    drives.inject("drive_fault", device=1, code=0x2310)
    assert _cycle_until(bus, lambda: bus.state is LifecycleState.FAULT, 10.0)
    assert bus.faults()["jaw"][0] == 0x2310
    states = bus.read()
    assert states["jaw"].fault_code == 0x2310 and states["jaw"].fault
    with pytest.raises(DeviceFault) as err:
        bus.write({"jaw": 0.0})
    assert err.value.device == "jaw" and err.value.code == 0x2310
    # Fault reset (controlword bit 7 edge) and back to work.
    bus.reset_fault()
    assert bus.state is LifecycleState.INACTIVE
    assert drives.drives[1].state == drv.SWITCH_ON_DISABLED
    bus.enable()
    start = {m.name: bus.read()[m.name].position for m in MOTORS}
    states = _run(bus, 0.4, lambda m, t: start[m.name] - 0.2 * min(t / 0.3, 1.0))
    assert states["jaw"].position == pytest.approx(start["jaw"] - 0.2, abs=5e-3)
    assert bus.state is LifecycleState.ACTIVE


def test_following_error_faults_with_8611(bus, drives):
    bus.open()
    bus.enable()
    _run(bus, 0.05, lambda m, t: bus.read()[m.name].position)
    drives.inject("following_error", device=2, counts=20_000)
    assert _cycle_until(bus, lambda: bus.state is LifecycleState.FAULT, 10.0)
    assert bus.faults()["lip"][0] == drv.EMCY_FOLLOWING_ERROR
    drives.inject("release", device=2)
    bus.reset_fault()
    bus.enable()
    assert bus.state is LifecycleState.ACTIVE


def test_silent_node_raises_bus_timeout_naming_it(drives):
    motors = (*MOTORS, MotorConfig.rotary("brow", 9, counts_per_rev=4096, min_position=-1, max_position=1,
                                           max_velocity=1.0))
    bus = _bus(drives, motors, node_timeout_s=0.3, sdo_timeout_s=0.05)
    t0 = time.monotonic()
    with pytest.raises(BusTimeout) as err:
        bus.open()
    assert time.monotonic() - t0 < 2.0
    assert err.value.device == "brow" and "node 9" in str(err.value)
    assert bus.state is LifecycleState.UNCONFIGURED
    bus.close()


@pytest.mark.parametrize(
    ("options", "key"),
    [
        ({"interface": "virtual", "bitrat": 500_000}, "bitrat"),
        ({"channel": "x"}, "interface"),
        ({"interface": "socketcand"}, "port"),
        ({"interface": "virtual", "heartbeat_timeout_s": 0.05, "heartbeat_period_s": 0.1}, "heartbeat_period_s"),
        ({"interface": "virtual", "heartbeat_timeout_s": -1}, "heartbeat_timeout_s"),
        ({"interface": "virtual", "stale_cycles": 2.5}, "stale_cycles"),
        ({"interface": "virtual", "bus_options": 3}, "bus_options"),
        ({"interface": "virtual", "tpdo2_every": 0}, "tpdo2_every"),
        ({"interface": "virtual", "tpdo2_every": 241}, "tpdo2_every"),
    ],
)
def test_bad_options_raise_config_error_naming_the_key(options, key):
    with pytest.raises(ConfigError) as err:
        create_bus("canopen402", "can0", options, MOTORS)
    assert err.value.key == key and key in str(err.value)


def test_bad_node_id_is_a_config_error():
    motor = MotorConfig.rotary("jaw", 200, counts_per_rev=4096, min_position=-1, max_position=1, max_velocity=1)
    with pytest.raises(ConfigError) as err:
        CanOpen402Bus("can0", {"interface": "virtual"}, [motor])
    assert "device_id" in err.value.key


def test_missing_socketcand_server_fails_fast():
    bus = CanOpen402Bus("can0", {"interface": "socketcand", "port": 1, "node_timeout_s": 0.2}, MOTORS)
    with pytest.raises(BusInitError, match="socketcand"):
        bus.open()


def test_dropped_and_corrupted_frames_are_tolerated_then_sustained_loss_faults(drives):
    bus = _bus(drives, heartbeat_timeout_s=0.4, heartbeat_period_s=0.02)
    try:
        bus.open()
        bus.enable()
        start = {m.name: bus.read()[m.name].position for m in MOTORS}
        drives.inject("frames", drop=0.2, corrupt=0.2, direction="tx", device=1)
        states = _run(bus, 0.6, lambda m, t: start[m.name] + 0.2 * min(t / 0.4, 1.0))
        assert bus.state is LifecycleState.ACTIVE
        assert bus.diagnostics()["malformed_tpdos"] > 0
        assert drives.network.impairment.counts["dropped"] > 0
        assert states["jaw"].position == pytest.approx(start["jaw"] + 0.2, abs=5e-3)
        # Corrupted RPDOs: the drive reports EMCY 0x8210, which is counted, not escalated.
        drives.inject("frames", corrupt=0.3, direction="rx", device=1)
        _run(bus, 0.3, lambda m, t: start[m.name] + 0.2)
        assert bus.diagnostics()["tolerated_emcy"] > 0
        assert bus.state is LifecycleState.ACTIVE
        # Everything from node 1 lost: feedback goes stale (or the heartbeat goes first) → FAULT naming jaw.
        drives.inject("frames", drop=1.0, direction="tx", device=1)
        assert _cycle_until(bus, lambda: bus.state is LifecycleState.FAULT, 10.0)
        assert bus.faults()["jaw"][0] in (FAULT_FEEDBACK_STALE, FAULT_HEARTBEAT_LOST)
    finally:
        bus.close()


def test_stale_feedback_with_heartbeat_alive_faults(drives):
    bus = _bus(drives, heartbeat_timeout_s=5.0, heartbeat_period_s=0.02, feedback_timeout_s=0.05)
    try:
        bus.open()
        bus.enable()
        # SYNCs from the master never reach the drives: no TPDOs, heartbeats keep coming.
        drives.inject("frames", drop=1.0, direction="rx")
        hold = {m.name: bus.read()[m.name].position for m in MOTORS}
        deadline = time.monotonic() + 2.0
        while bus.state is LifecycleState.ACTIVE and time.monotonic() < deadline:
            bus.read()
            if bus.state is LifecycleState.ACTIVE:
                bus.write(hold)
            time.sleep(0.005)
        assert bus.state is LifecycleState.FAULT
        assert {code for code, _ in bus.faults().values()} == {FAULT_FEEDBACK_STALE}
    finally:
        bus.close()


def test_node_reboot_faults_and_reset_reconfigures(bus, drives):
    bus.open()
    bus.enable()
    drives.drives[2].reset(application=True)  # as after a power glitch: boot-up, defaults, pre-operational
    assert _cycle_until(bus, lambda: bus.state is LifecycleState.FAULT, 10.0)
    assert bus.faults()["lip"][0] == FAULT_NODE_STATE
    bus.reset_fault()
    assert drives.drives[2].nmt_state == "OPERATIONAL"
    bus.enable()
    start = {m.name: bus.read()[m.name].position for m in MOTORS}
    states = _run(bus, 0.3, lambda m, t: start[m.name] + 0.1 * min(t / 0.2, 1.0))
    assert states["lip"].position == pytest.approx(start["lip"] + 0.1, abs=5e-3)


def test_over_socketcand_in_one_process(drives):
    server = SocketcandServer(bus_kwargs={"interface": "virtual", "channel": drives.channel}, port=0).start()
    bus = CanOpen402Bus("can0", {"interface": "socketcand", "port": server.port, "channel": "can0", **PATIENT}, MOTORS)
    try:
        bus.open()
        bus.enable()
        start = {m.name: bus.read()[m.name].position for m in MOTORS}
        states = _run(bus, 0.5, lambda m, t: start[m.name] + 0.2 * min(t / 0.3, 1.0))
        assert states["jaw"].position == pytest.approx(start["jaw"] + 0.2, abs=5e-3)
        assert bus.state is LifecycleState.ACTIVE
    finally:
        bus.close()
        server.stop()


def test_frames_sent_together_over_socketcand_arrive_whole_and_in_order():
    """A cycle's frames cross the bridge as one TCP write (``send_frames``): on the CAN side, each frame as sent."""
    import can
    import canopen

    from drivers.canopen402 import send_frames

    channel = f"test-batch-{uuid.uuid4().hex[:10]}"
    server = SocketcandServer(bus_kwargs={"interface": "virtual", "channel": channel}, port=0).start()
    listener = can.Bus(interface="virtual", channel=channel)
    net = canopen.Network(can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel="can0"))
    net.connect()
    frames = [(0x201, bytes([0x0F, 0x00, 0x10, 0x27, 0x00, 0x00])), (0x202, bytes(range(250, 256)) + b"\x00\x01"),
              (0x203, b"\x00"), (0x80, b"")]
    try:
        for _ in range(3):
            send_frames(net, frames)
        got = []
        deadline = time.monotonic() + 10.0
        while len(got) < 3 * len(frames) and time.monotonic() < deadline:
            msg = listener.recv(0.5)
            if msg is not None:
                got.append((msg.arbitration_id, bytes(msg.data)))
        assert got == 3 * frames
    finally:
        net.disconnect()
        listener.shutdown()
        server.stop()


def test_sample_head_can_bus_in_process():
    """The runtime's path: the sample head's can0 actuators on emulated drives, driver on the same channel."""
    from models.headspec import load_head

    head = load_head(Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml")
    spec = head.buses["can0"]
    actuators = head.actuators_on("can0")
    motors = [
        MotorConfig.rotary(a.name, a.device_id, counts_per_rev=a.counts_per_rev, gear_ratio=a.gear_ratio,
                           direction=a.direction, zero_count=a.zero_count, min_position=a.min, max_position=a.max,
                           max_velocity=a.max_velocity)
        for a in actuators
    ]
    options = {**spec.driver_options(), **PATIENT, "channel": f"test-sample-{uuid.uuid4().hex[:8]}"}
    with DriveSet([a.device_id for a in actuators], channel=options["channel"]) as ds:
        bus = create_bus(spec.driver, "can0", options, motors)
        try:
            bus.open()
            bus.enable()
            neutral = {a.name: a.neutral for a in actuators}
            goal = {a.name: min(a.neutral + 0.1, a.max) for a in actuators}
            start = time.monotonic()
            while (t := time.monotonic() - start) < 0.5:
                bus.read()
                f = min(t / 0.3, 1.0)
                bus.write({n: neutral[n] + (goal[n] - neutral[n]) * f for n in neutral})
                time.sleep(0.005)
            states = bus.read()
            for a in actuators:
                assert states[a.name].position == pytest.approx(goal[a.name], abs=5e-3), a.name
                truth = bus.motors[a.name].from_counts(ds.drives[a.device_id].position_counts)
                assert truth == pytest.approx(goal[a.name], abs=5e-3), a.name
        finally:
            bus.close()


def test_optional_drive_parameters_are_written(drives):
    bus = _bus(drives, cycle_period_s=0.005, following_error_window_counts=8000, heartbeat_period_s=0.01)
    try:
        bus.open()
        for drive in drives.drives.values():
            assert drive._get(0x60C2, 1) == 5 and drive._get(0x60C2, 2) == -3
            assert drive._get(0x6065) == 8000
            assert drive.node.nmt.heartbeat_time_ms == 10
            assert drive._get(0x6061) == 8  # CSP
        # the configured limits (±1 rad) as the drives' software position limits, in counts (lip runs reversed)
        for node_id, gear in ((1, 10.0), (2, 5.0)):
            counts = round(4096 * gear / (2 * math.pi))
            drive = drives.drives[node_id]
            assert (drive._get(0x607D, 1), drive._get(0x607D, 2)) == (-counts, counts)
    finally:
        bus.close()
    # close leaves the drives pre-operational (no PDO processing without a master); each drive takes the NMT
    # command on its own bus thread, after close has returned
    wait_until(lambda: all(d.nmt_state == "PRE-OPERATIONAL" for d in drives.drives.values()), 10.0,
               "every drive PRE-OPERATIONAL after close")
