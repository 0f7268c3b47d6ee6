"""The emulated servo on a manual clock: control-table rules from the e-manual and the motion model."""

from __future__ import annotations

import math

import pytest

from sim_hardware.dynamixel.control_table import MODELS, ModelSpec, get_model, register_model, xm430_w350
from sim_hardware.dynamixel.protocol import ALERT_BIT, HardwareError, ResultError
from sim_hardware.dynamixel.servo import Servo


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def u32(v: int) -> bytes:
    return (v & 0xFFFFFFFF).to_bytes(4, "little")


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def servo(clock: Clock) -> Servo:
    return Servo(get_model("XM430-W350"), 1, initial_position=1000, clock=clock)


def present(servo: Servo, clock: Clock) -> int:
    error, data = servo.read(132, 4)
    assert error == 0
    return int.from_bytes(data, "little", signed=True)


def test_defaults_follow_the_manual(servo: Servo) -> None:
    assert servo.read_item("model_number") == 1020
    assert servo.read_item("id") == 1
    assert servo.read_item("return_delay_time") == 250
    assert servo.read_item("operating_mode") == 3
    assert servo.read_item("temperature_limit") == 80
    assert servo.read_item("current_limit") == 1193
    assert servo.read_item("velocity_limit") == 200
    assert servo.read_item("max_position_limit") == 4095
    assert servo.read_item("min_position_limit") == 0
    assert servo.read_item("shutdown") == 52
    assert servo.read_item("status_return_level") == 2
    spec = get_model("XM430-W350")
    assert [spec.address(n) for n in ("torque_enable", "led", "hardware_error_status", "goal_pwm", "goal_current",
                                      "goal_velocity", "profile_acceleration", "profile_velocity", "goal_position",
                                      "realtime_tick", "moving", "present_current", "present_velocity",
                                      "present_position", "present_input_voltage", "present_temperature")] == [
        64, 65, 70, 100, 102, 104, 108, 112, 116, 120, 122, 126, 128, 132, 144, 146]


def test_access_rules(servo: Servo) -> None:
    assert servo.write(0, b"\x01\x02") & 0x7F == ResultError.ACCESS  # model number is read-only
    assert servo.write(14, b"\x00") & 0x7F == ResultError.ACCESS  # unused gap
    assert servo.write(116, b"\x01\x02") & 0x7F == ResultError.DATA_LENGTH  # half a 4-byte item
    assert servo.write(11, b"\x02") & 0x7F == ResultError.DATA_RANGE  # no operating mode 2
    assert servo.write(64, b"\x01") == 0
    assert servo.write(11, b"\x04") & 0x7F == ResultError.ACCESS  # EEPROM locked while torque is on
    assert servo.write(116, u32(5000)) & 0x7F == ResultError.DATA_LIMIT  # beyond max position limit
    assert servo.write(104, u32(300)) & 0x7F == ResultError.DATA_LIMIT  # in range, above velocity limit 200
    assert servo.write(104, u32(3000)) & 0x7F == ResultError.DATA_RANGE  # outside -1023..1023
    assert servo.write(64, b"\x00") == 0
    assert servo.write(11, b"\x04") == 0
    assert servo.read_item("operating_mode") == 4
    assert servo.write(116, u32(5000)) == 0  # extended position mode has no position limit


def test_velocity_limit_is_a_data_limit(servo: Servo) -> None:
    servo.write(11, b"\x01")
    assert servo.write(104, u32(150)) == 0
    assert servo.write(104, u32(250)) & 0x7F == ResultError.DATA_LIMIT  # above velocity limit 200


def test_multi_item_write_is_all_or_nothing(servo: Servo) -> None:
    # profile acceleration (108) + profile velocity (112) + goal position (116) in one write
    ok = u32(10) + u32(100) + u32(1500)
    assert servo.write(108, ok) == 0
    assert servo.read_item("profile_velocity") == 100
    bad = u32(20) + u32(200) + u32(9000)  # goal beyond the position limit
    assert servo.write(108, bad) & 0x7F == ResultError.DATA_LIMIT
    assert servo.read_item("profile_acceleration") == 10  # nothing applied


def test_goal_reached_with_profile_velocity(servo: Servo, clock: Clock) -> None:
    servo.write(112, u32(100))  # 100 × 0.229 rpm = 1563 counts/s
    servo.write(116, u32(2000))
    servo.write(64, b"\x01")
    speed = 100 * 0.229 * 4096 / 60
    clock.t += 0.3
    p = present(servo, clock)
    assert abs(p - (1000 + speed * 0.3)) <= 2
    assert servo.read_item("moving") == 1
    assert int.from_bytes(servo.read(128, 4)[1], "little", signed=True) == 100
    clock.t += 1.0
    assert present(servo, clock) == 2000
    assert servo.read_item("moving") == 0
    assert servo.read_item("moving_status") & 0x01  # in position


def test_trapezoidal_profile_acceleration(servo: Servo, clock: Clock) -> None:
    servo.write(108, u32(10))  # 10 × 214.577 rev/min² = 2441 counts/s²
    servo.write(112, u32(100))
    servo.write(116, u32(3000))
    servo.write(64, b"\x01")
    acc = 10 * 214.577 * 4096 / 3600
    clock.t += 0.2
    p = present(servo, clock)
    assert abs(p - (1000 + 0.5 * acc * 0.2**2)) < 10  # still accelerating: s = a t² / 2
    for _ in range(400):
        clock.t += 0.01
        servo.advance()
    assert present(servo, clock) == 3000


def test_torque_off_means_no_motion(servo: Servo, clock: Clock) -> None:
    servo.write(116, u32(3000))
    clock.t += 2.0
    assert present(servo, clock) == 1000
    servo.set_shaft_position(1234)  # back-driven by the mechanism
    assert present(servo, clock) == 1234
    assert math.isclose(servo.position_rad(), 1234 * 2 * math.pi / 4096)


def test_velocity_mode(servo: Servo, clock: Clock) -> None:
    servo.write(11, b"\x01")
    servo.write(104, u32(-50))
    servo.write(64, b"\x01")
    clock.t += 1.0
    assert abs(present(servo, clock) - (1000 - 50 * 0.229 * 4096 / 60)) <= 1


def test_overheat_sets_alert_turns_torque_off_and_reboot_clears(servo: Servo, clock: Clock) -> None:
    servo.write(64, b"\x01")
    servo.temperature = 95.0
    error, data = servo.read(70, 1)
    assert error == ALERT_BIT and data[0] == HardwareError.OVERHEATING
    assert not servo.torque_enabled
    assert servo.read(146, 1)[1][0] == 95
    assert servo.write(64, b"\x01") & 0x7F == ResultError.RESULT_FAIL  # no torque until reboot
    servo.reboot(0.0)
    assert servo.hardware_error == HardwareError.OVERHEATING  # still hot: the error comes straight back
    servo.temperature = 30.0
    servo.reboot(0.0)
    servo.advance()
    assert servo.hardware_error == 0 and servo.alert == 0


def test_input_voltage_error_not_in_default_shutdown(servo: Servo) -> None:
    servo.write(64, b"\x01")
    servo.voltage = 6.0
    servo.advance()
    assert servo.hardware_error == HardwareError.INPUT_VOLTAGE
    assert servo.torque_enabled  # shutdown 52 does not include input voltage
    assert servo.read(144, 2)[1] == (60).to_bytes(2, "little")


def test_overload_holds_current_at_limit(servo: Servo) -> None:
    servo.write(64, b"\x01")
    servo.overload_condition = True
    servo.advance()
    assert servo.hardware_error == HardwareError.OVERLOAD
    assert not servo.torque_enabled


def test_cooling_ends_overheat_condition(servo: Servo, clock: Clock) -> None:
    servo.temperature = 85.0
    servo.advance()
    clock.t += 30.0  # one thermal time constant: 25 + 60/e ≈ 47 °C
    servo.advance()
    assert 45 < servo.temperature < 50
    servo.reboot(0.0)
    assert servo.hardware_error == 0


def test_indirect_addressing(servo: Servo) -> None:
    mapping = b"".join(a.to_bytes(2, "little") for a in (70, 64, 132, 133, 134, 135))
    assert servo.write(168, mapping) == 0
    error, data = servo.read(224, 6)
    assert error == 0 and data == bytes((0, 0)) + (1000).to_bytes(4, "little")
    # writing through indirect data reaches the real item
    assert servo.write(168, (116).to_bytes(2, "little") + (117).to_bytes(2, "little")
                       + (118).to_bytes(2, "little") + (119).to_bytes(2, "little")) == 0
    assert servo.write(224, u32(1777)) == 0
    assert servo.read_item("goal_position") == 1777
    servo.write(64, b"\x01")
    assert servo.write(168, b"\x46\x00") & 0x7F == ResultError.ACCESS  # locked while torque on


def test_reg_write_and_action(servo: Servo) -> None:
    assert servo.action() & 0x7F == ResultError.INSTRUCTION
    assert servo.reg_write(65, b"\x01") == 0
    assert servo.read_item("registered_instruction") == 1
    assert servo.read_item("led") == 0
    assert servo.action() == 0
    assert servo.read_item("led") == 1
    assert servo.read_item("registered_instruction") == 0


def test_factory_reset_options(servo: Servo) -> None:
    servo.write(7, b"\x05")
    servo.write(9, b"\x00")
    assert servo.factory_reset(0x01) == 0
    assert servo.device_id == 5 and servo.read_item("return_delay_time") == 250
    assert servo.factory_reset(0xFF) == 0
    assert servo.device_id == 1
    assert servo.factory_reset(0x07) & 0x7F == ResultError.DATA_RANGE


def test_homing_offset_shifts_present_position(servo: Servo, clock: Clock) -> None:
    servo.write(20, u32(-200))
    assert present(servo, clock) == 800
    servo.write(116, u32(900))
    servo.write(64, b"\x01")
    clock.t += 1.0
    assert present(servo, clock) == 900
    assert round(servo.shaft) == 1100


def test_models_are_pluggable() -> None:
    assert get_model("XM430-W210").model_number == 1030
    with pytest.raises(ValueError, match="unknown Dynamixel model 'XX-1'"):
        get_model("XX-1")
    base = xm430_w350()
    register_model("TEST-1", lambda: ModelSpec("TEST-1", 4242, 1, base.items))
    try:
        assert get_model("TEST-1").model_number == 4242
    finally:
        MODELS.pop("TEST-1")
