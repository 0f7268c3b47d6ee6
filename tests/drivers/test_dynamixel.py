"""``DynamixelBus`` back to back with the in-process emulator: configuration, cyclic I/O, faults, recovery."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.base import LifecycleState, MotorConfig
from drivers.dynamixel import FAULT_COMMUNICATION, FAULT_TORQUE_LOST, DynamixelBus
from drivers.errors import BusInitError, BusTimeout, CommandRejected, ConfigError, DeviceFault
from drivers.registry import create_bus
from sim_hardware.dynamixel import DynamixelEmulator
from tests._wait import wait_until

IDS = (1, 2, 3, 4)
RAD_PER_COUNT = 2 * math.pi / 4096


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    """Widen the SDK's answer window (2 × latency timer + 2 ms) so a loaded test machine does not flake."""
    import dynamixel_sdk.port_handler

    monkeypatch.setattr(dynamixel_sdk.port_handler, "LATENCY_TIMER", 50)


def motors(ids=IDS, zero: int = 2048, lo: float = -0.6, hi: float = 0.6, vmax: float = 4.0) -> list[MotorConfig]:
    return [MotorConfig.rotary(f"m{i}", i, counts_per_rev=4096, min_position=lo, max_position=hi,
                               max_velocity=vmax, zero_count=zero, direction=1 if i % 2 else -1) for i in ids]


@pytest.fixture
def emu() -> Iterator[DynamixelEmulator]:
    with DynamixelEmulator(IDS, initial_positions=2048, reboot_time_s=0.05) as e:
        yield e


def make_bus(emu: DynamixelEmulator, **options) -> DynamixelBus:
    opts = {"port": emu.port, "baudrate": 4_000_000, "model": "XM430-W350", **options}
    return DynamixelBus("dxl", opts, motors())


@pytest.fixture
def bus(emu: DynamixelEmulator) -> Iterator[DynamixelBus]:
    b = make_bus(emu)
    b.open()
    yield b
    b.close()


def ramp(bus: DynamixelBus, targets: dict[str, float], seconds: float) -> None:
    """Stream a rate-limited ramp from the present positions to ``targets``."""
    start = {n: s.position for n, s in bus.read().items()}
    t0 = time.monotonic()
    while True:
        a = min(1.0, (time.monotonic() - t0) / seconds)
        bus.write({n: start[n] + a * (targets[n] - start[n]) for n in targets})
        bus.read()
        if a >= 1.0:
            return
        time.sleep(0.005)


def test_registry_and_open_configures_servos(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    assert isinstance(create_bus("dynamixel", "x", {"port": "/dev/null"}, motors()), DynamixelBus)
    assert bus.state is LifecycleState.INACTIVE
    assert bus.operating_mode == 3 and bus.uses_fast_sync_read
    for i in IDS:
        servo = emu.servo(i)
        assert servo.read_item("operating_mode") == 3
        assert servo.read_item("return_delay_time") == 0
        lo, hi = sorted((2048 + round(-0.6 * 4096 / (2 * math.pi)) * (1 if i % 2 else -1),
                         2048 + round(0.6 * 4096 / (2 * math.pi)) * (1 if i % 2 else -1)))
        assert (servo.read_item("min_position_limit"), servo.read_item("max_position_limit")) == (lo, hi)
        wanted = math.ceil(4.0 * 4096 / (2 * math.pi) / (0.229 * 4096 / 60))  # max velocity, 167 units: a cap only
        assert servo.read_item("profile_velocity") == min(wanted, servo.read_item("velocity_limit"))
        assert servo.read_item("profile_acceleration") == 0  # no acceleration ramp of the servo's own
        assert not servo.torque_enabled
    states = bus.read()
    assert set(states) == {f"m{i}" for i in IDS}
    assert all(abs(s.position) < 1e-9 and not s.enabled and s.fault_code == 0 for s in states.values())


@pytest.mark.parametrize("fast", [True, False])
def test_enable_write_read_tracks_targets(emu: DynamixelEmulator, fast: bool) -> None:
    bus = make_bus(emu, use_fast_sync_read=fast)
    with bus:
        emu.servo(3).set_shaft_position(2048 + 100)  # one motor starts off-centre
        bus.enable()
        states = bus.read()
        assert all(s.enabled for s in states.values())
        assert math.isclose(states["m3"].position, 100 * RAD_PER_COUNT)
        assert emu.servo(3).read_item("goal_position") == 2148  # torque on holding the present position
        targets = {"m1": 0.4, "m2": -0.3, "m3": 0.2, "m4": 0.5}
        ramp(bus, targets, 0.3)
        # the servos settle on the last targets
        wait_until(lambda: all(abs(s.position - targets[n]) <= 1.5 * RAD_PER_COUNT for n, s in bus.read().items()),
                   10.0, "every servo within 1.5 counts of its target")
        truth = emu.positions()
        assert abs(truth[2] - (2048 + 0.3 * 4096 / (2 * math.pi))) <= 1  # direction -1: counts go up
        assert abs(truth[1] - (2048 + 0.4 * 4096 / (2 * math.pi))) <= 1
        bus.disable()
        assert wait_until(lambda: not any(emu.servo(i).torque_enabled for i in IDS), 10)


def test_velocity_and_effort_in_si(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    bus.enable()
    emu.servo(1).write_item("goal_position", 2048 + 2000)  # a big step behind the guard, to see motion
    emu.servo(1).write_item("max_position_limit", 4095)
    speed_limit = min(167, emu.servo(1).read_item("velocity_limit")) * 0.229 * 2 * math.pi / 60  # profile velocity
    # well under way (at the start of the step the current saturates), as after 50 ms at the profile velocity
    state = wait_until(lambda: (st := bus.read()["m1"]).position > 0.15 and st, 10.0, "m1 under way (0.15 rad)")
    assert 0.5 * speed_limit < state.velocity <= speed_limit * 1.01
    assert state.effort != 0.0 and abs(state.effort) < 1193 * 2.69e-3


def test_limit_and_rate_guards_never_reach_the_bus(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    with pytest.raises(Exception, match="needs state active"):
        bus.write({"m1": 0.0})
    bus.enable()
    for bad, match in (({"m1": 0.7}, "outside"), ({"m1": float("nan")}, "not finite"), ({"m9": 0.0}, "unknown"),
                       ({"m1": 0.5}, "exceeds max_velocity")):
        with pytest.raises(CommandRejected, match=match):
            bus.write(bad)
    assert all(emu.servo(i).read_item("goal_position") == 2048 for i in IDS)
    # the servos themselves also refuse goals beyond the configured range (position limits set at open)
    assert emu.servo(1).write(116, (4000).to_bytes(4, "little")) & 0x7F == 6


@pytest.mark.parametrize(("fault", "code"), [("overheat", 0x04), ("overload", 0x20), ("voltage", 0x01)])
def test_hardware_fault_then_reboot_recovery(bus: DynamixelBus, emu: DynamixelEmulator, fault: str, code: int) -> None:
    bus.enable()
    emu.inject(fault, 2)
    states = bus.read()
    assert bus.state is LifecycleState.FAULT
    assert bus.faults()["m2"][0] == code
    assert states["m2"].fault_code == code
    assert wait_until(lambda: not any(emu.servo(i).torque_enabled for i in IDS), 10)  # every servo in the safe state
    with pytest.raises(DeviceFault) as err:
        bus.write({"m1": 0.0})
    assert err.value.code == code
    if fault != "voltage":  # the condition persists: the reboot does not clear it
        with pytest.raises(DeviceFault, match="after reboot"):
            bus.reset_fault()
        assert bus.state is LifecycleState.FAULT
    emu.clear(fault, 2)
    bus.reset_fault()
    assert bus.state is LifecycleState.INACTIVE and not bus.faults()
    assert emu.servo(2).hardware_error == 0
    assert emu.servo(2).read_item("indirect_address_1") == 70  # configured again after the reboot
    bus.enable()
    assert all(s.enabled and not s.fault for s in bus.read().values())


def test_latched_error_needs_reboot(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    emu.inject("electrical_shock", 4)
    bus.read()
    assert bus.faults()["m4"][0] == 0x10
    bus.reset_fault()  # the reboot clears a latched error
    assert bus.state is LifecycleState.INACTIVE


def test_torque_lost_is_a_fault(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    bus.enable()
    emu.servo(3).reboot(0.0)  # power blip behind the driver's back
    bus.read()
    assert bus.state is LifecycleState.FAULT
    assert bus.faults()["m3"][0] == FAULT_TORQUE_LOST


def test_missing_id_is_a_bus_timeout_naming_it(emu: DynamixelEmulator) -> None:
    bus = DynamixelBus("dxl", {"port": emu.port, "retries": 1}, motors((1, 2, 9)))
    t = time.monotonic()
    with pytest.raises(BusTimeout) as err:
        bus.open()
    assert err.value.device == "m9" and "id 9: no answer to ping" in str(err.value)
    assert time.monotonic() - t < 2.0
    assert bus.state is LifecycleState.UNCONFIGURED


def test_communication_loss_faults_after_consecutive_failures(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    bus.enable()
    good = bus.read()
    emu.inject("disconnect", 2)
    for _ in range(2):  # tolerated: the last states come back with their old timestamps
        stale = bus.read()
        assert stale == good and bus.state is LifecycleState.ACTIVE
    with pytest.raises(BusTimeout):
        bus.read()
    assert bus.state is LifecycleState.FAULT
    (device, (code, _)), = bus.faults().items()
    assert code == FAULT_COMMUNICATION and device in ("dxl", "m2")
    assert wait_until(lambda: not emu.servo(1).torque_enabled, 10)
    emu.clear("disconnect")
    bus.reset_fault()
    assert bus.state is LifecycleState.INACTIVE


def test_drop_rate_below_threshold_is_survived(emu: DynamixelEmulator) -> None:
    bus = make_bus(emu, max_consecutive_failures=50)
    with bus:
        bus.enable()
        emu.inject("drop", rate=0.3)
        for _ in range(10):
            bus.read()
        emu.clear()
        assert bus.state is LifecycleState.ACTIVE


def test_wrong_model_is_refused() -> None:
    with DynamixelEmulator([1], model="XM430-W210") as other:
        bus = DynamixelBus("dxl", {"port": other.port, "model": "XM430-W350"}, motors((1,)))
        with pytest.raises(BusInitError, match="model number 1030"):
            bus.open()


def test_enable_refuses_a_motor_outside_its_range(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    emu.servo(1).set_shaft_position(2048 + 1000)  # 1.53 rad, beyond 0.6
    with pytest.raises(CommandRejected, match="m1: present position"):
        bus.enable()
    assert bus.state is LifecycleState.INACTIVE and not emu.servo(1).torque_enabled


@pytest.mark.parametrize(("options", "key"), [
    ({"baudrate": 123}, "baudrate"),
    ({"protocol": 1.0}, "protocol"),
    ({"model": "AX-12"}, "model"),
    ({"return_delay_us": 3}, "return_delay_us"),
    ({"return_delay_us": 600}, "return_delay_us"),
    ({"use_fast_sync_read": "yes"}, "use_fast_sync_read"),
    ({"operating_mode": "velocity"}, "operating_mode"),
    ({"max_consecutive_failures": 0}, "max_consecutive_failures"),
    ({"reboot_timeout_s": -1}, "reboot_timeout_s"),
    ({"bogus": 1}, "options"),
    ({"port": ""}, "port"),
])
def test_bad_options_are_config_errors(options: dict, key: str) -> None:
    with pytest.raises(ConfigError) as err:
        DynamixelBus("dxl", {"port": "/dev/null", **options}, motors())
    assert key in err.value.key


def test_fast_sync_read_only_while_the_answer_fits_one_sdk_packet() -> None:
    many = motors(range(1, 80))
    assert not DynamixelBus("dxl", {"port": "/dev/null"}, many).uses_fast_sync_read
    assert DynamixelBus("dxl", {"port": "/dev/null"}, motors(range(1, 41))).uses_fast_sync_read
    with pytest.raises(ConfigError, match="exceeds"):
        DynamixelBus("dxl", {"port": "/dev/null", "use_fast_sync_read": True}, many)


def test_position_mode_range_check_and_auto_mode() -> None:
    sample_like = motors(zero=0, lo=-0.4, hi=0.6)  # negative counts: outside 0..4095
    with pytest.raises(ConfigError, match=r"m1.*extended_position"):
        DynamixelBus("dxl", {"port": "/dev/null", "operating_mode": "position"}, sample_like)
    assert DynamixelBus("dxl", {"port": "/dev/null"}, sample_like).operating_mode == 4
    assert DynamixelBus("dxl", {"port": "/dev/null"}, motors()).operating_mode == 3


def test_bad_port_is_a_bus_init_error(tmp_path: Path) -> None:
    bus = DynamixelBus("dxl", {"port": str(tmp_path / "nothing")}, motors())
    with pytest.raises(BusInitError, match="cannot open port"):
        bus.open()
    with pytest.raises(ConfigError, match="auto"):
        DynamixelBus("dxl", {"port": "auto"}, motors()).open()


def test_sample_head_dxl_bus_in_process() -> None:
    """The sample head's Dynamixel bus (zero_count 0, negative minima) runs on an in-process emulator."""
    from models.headspec import load_head

    head = load_head(Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml")
    spec = head.buses["dxl"]
    actuators = head.actuators_on("dxl")
    configs = [MotorConfig.rotary(a.name, a.device_id, counts_per_rev=a.counts_per_rev, min_position=a.min,
                                  max_position=a.max, max_velocity=a.max_velocity, gear_ratio=a.gear_ratio,
                                  direction=a.direction, zero_count=a.zero_count) for a in actuators]
    with DynamixelEmulator([a.device_id for a in actuators], spec.options["model"]) as emu:
        bus = create_bus(spec.driver, "dxl", {**spec.options, "port": emu.port}, configs)
        with bus:
            bus.enable()
            assert bus.operating_mode == 4
            first = actuators[0]
            ramp(bus, {first.name: first.max * 0.5}, 0.3)
            wait_until(lambda: abs(bus.read()[first.name].position - first.max * 0.5) < 2 * RAD_PER_COUNT, 10.0,
                       f"{first.name} within 2 counts of its target")


def test_concurrent_use_is_serialised(bus: DynamixelBus) -> None:
    bus.enable()
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            for _ in range(40):
                bus.read()
        except BaseException as exc:  # collected for the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    for _ in range(40):
        bus.write({"m1": 0.0, "m2": 0.0})
    for t in threads:
        t.join()
    assert not errors and bus.state is LifecycleState.ACTIVE


def test_wire_budget_arithmetic_matches_measured_bus_physics() -> None:
    """Write + sync read (4-byte position) of 13 servos: ≈ 330 Hz @1M, 1.3 kHz @4M, 105 Hz with 500 µs delay."""
    from benchmarks._bus_dynamixel import bus_budget_s

    assert 1 / bus_budget_s(13, 1_000_000, fast=False, data=4) == pytest.approx(330, rel=0.02)
    assert 1 / bus_budget_s(13, 4_000_000, fast=False, data=4) == pytest.approx(1330, rel=0.02)
    assert 1 / bus_budget_s(13, 1_000_000, 500.0, fast=False, data=4) == pytest.approx(105, rel=0.02)
    assert bus_budget_s(40, 1_000_000) > bus_budget_s(13, 1_000_000)


def test_return_delay_option_is_written_and_honoured(emu: DynamixelEmulator) -> None:
    bus = make_bus(emu, return_delay_us=300)
    with bus:
        assert all(emu.servo(i).read_item("return_delay_time") == 150 for i in IDS)
        start = time.perf_counter()
        bus.read()
        assert time.perf_counter() - start >= 300e-6  # at least one servo's delay before the answer


def test_fault_during_enable_is_not_overwritten_by_active(bus: DynamixelBus, emu: DynamixelEmulator) -> None:
    original = bus._enable

    def enable_then_overheat() -> None:
        original()
        emu.inject("overheat", 1)  # appears between torque on and the enable's own read

    bus._enable = enable_then_overheat  # type: ignore[method-assign]
    with pytest.raises(DeviceFault, match="while enabling"):
        bus.enable()
    assert bus.state is LifecycleState.FAULT and bus.faults()["m1"][0] == 0x04
    assert wait_until(lambda: not any(emu.servo(i).torque_enabled for i in IDS), 10)


def test_a_transaction_the_sdk_aborts_leaves_the_port_usable(bus: DynamixelBus) -> None:
    """The SDK marks its port busy for a transaction and clears the mark only when the transaction ends normally; one
    that raises half way (a pseudo-terminal closing under it) must not leave every later one answering "Port is in
    use!" without touching the port, which would hide a lost port from the reconnect logic."""
    port = bus._port

    def aborted() -> None:
        port.is_using = True  # as the SDK's txPacket does first
        raise IndexError("status packet cut short")

    with pytest.raises(IndexError):
        bus._call(aborted)
    assert port.is_using is False
    assert set(bus.read()) == {m.name for m in motors()}  # the next transaction reaches the servos
