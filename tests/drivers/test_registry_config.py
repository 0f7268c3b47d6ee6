"""Bus configuration is validated at load: unknown backends, duplicate ids, bad units name the key."""

from __future__ import annotations

import math

import pytest

from drivers import ConfigError, LifecycleError, MotorConfig, available_backends, create_bus
from drivers.base import LifecycleState


def motor(name: str = "jaw", device_id: int = 1, **kw) -> MotorConfig:
    args = dict(counts_per_rev=4096, min_position=-1.0, max_position=1.0, max_velocity=3.0)
    args.update(kw)
    return MotorConfig.rotary(name, device_id, **args)


def test_registry_lists_both_backends_and_refuses_unknown() -> None:
    assert available_backends() == ["canopen402", "dynamixel"]
    with pytest.raises(ConfigError) as info:
        create_bus("stepper9000", "bus0", {}, [motor()])
    assert info.value.key == "driver"
    assert "stepper9000" in str(info.value) and "canopen402" in str(info.value)


@pytest.mark.parametrize("driver", ["canopen402", "dynamixel"])
def test_duplicate_ids_and_names_are_refused(driver: str) -> None:
    with pytest.raises(ConfigError, match="duplicate device id 1"):
        create_bus(driver, "bus0", {"port": "/dev/null", "channel": "x"}, [motor("a", 1), motor("b", 1)])
    with pytest.raises(ConfigError, match="duplicate motor name 'a'"):
        create_bus(driver, "bus0", {"port": "/dev/null", "channel": "x"}, [motor("a", 1), motor("a", 2)])


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"counts_per_rev": 0}, "counts_per_rev"),
        ({"gear_ratio": -2.0}, "gear_ratio"),
        ({"direction": 0}, "direction"),
        ({"min_position": 2.0}, "min_position"),
        ({"max_velocity": 0.0}, "max_velocity"),
        ({"max_velocity": math.inf}, "max_velocity"),
    ],
)
def test_bad_motor_units_name_the_key(kwargs: dict, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        motor(**kwargs)
    assert key in info.value.key


def test_counts_round_trip_honours_gear_direction_and_zero() -> None:
    m = motor(gear_ratio=10.0, direction=-1, zero_count=2048)
    assert m.to_counts(0.0) == 2048
    assert m.to_counts(math.pi) == 2048 - 4096 * 5
    assert math.isclose(m.from_counts(m.to_counts(0.3)), 0.3, abs_tol=1e-3)


def test_closed_bus_refuses_io() -> None:
    bus = create_bus("dynamixel", "dxl", {"port": "/dev/null"}, [motor()])
    assert bus.state is LifecycleState.UNCONFIGURED
    with pytest.raises(LifecycleError, match="read needs an open bus"):
        bus.read()
    with pytest.raises(LifecycleError, match="write needs state active"):
        bus.write({"jaw": 0.0})
    with pytest.raises(LifecycleError, match="enable needs state inactive"):
        bus.enable()
