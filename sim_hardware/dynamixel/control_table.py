"""Control tables of emulated Dynamixel models (addresses, sizes, access, defaults, ranges).

The XM430-W350 table follows the public ROBOTIS e-manual (X-series, protocol 2.0): EEPROM
items 0–63 are writable only while torque is off, RAM items from 64 on. Other models register
a :class:`ModelSpec` under their name in :data:`MODELS`; the servo emulator only reads specs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

#: Operating modes of the X series (address 11).
MODE_CURRENT = 0
MODE_VELOCITY = 1
MODE_POSITION = 3
MODE_EXTENDED_POSITION = 4
MODE_CURRENT_BASED_POSITION = 5
MODE_PWM = 16

#: Baud rate item (address 8) → bits per second.
BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000, 7: 4_500_000}


@dataclass(frozen=True, slots=True)
class Item:
    """One control-table item: ``size`` bytes at ``address``; ``access`` is "R" or "RW".

    ``low``/``high`` bound writes (data range error outside); ``allowed`` lists the only legal
    values when the item is an enumeration. ``signed`` items are two's complement.
    """

    name: str
    address: int
    size: int
    access: str
    default: int = 0
    low: int | None = None
    high: int | None = None
    signed: bool = False
    allowed: frozenset[int] | None = None

    @property
    def eeprom(self) -> bool:
        return self.address < 64

    @property
    def writable(self) -> bool:
        return "W" in self.access


@dataclass(frozen=True)
class ModelSpec:
    """A servo model: identity, unit scales, motion limits and its control table."""

    name: str
    model_number: int
    firmware_version: int
    items: tuple[Item, ...]
    counts_per_rev: int = 4096
    velocity_unit_rpm: float = 0.229  # one Present/Goal/Profile Velocity unit
    acceleration_unit_rpm2: float = 214.577  # one Profile Acceleration unit (rev/min²)
    current_unit_a: float = 2.69e-3  # one Present/Goal Current unit
    voltage_unit_v: float = 0.1
    no_load_speed_rpm: float = 46.0  # at 12 V; caps velocity when profile velocity is 0
    extended_position_limit: int = 1_048_575
    indirect_address_blocks: tuple[tuple[int, int, int], ...] = ((168, 224, 28), (578, 634, 28))
    supports_fast_sync_read: bool = True
    size: int = 700
    _by_name: dict[str, Item] = field(init=False, repr=False, compare=False)
    _by_address: dict[int, Item] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_name", {it.name: it for it in self.items})
        object.__setattr__(self, "_by_address", {it.address: it for it in self.items})

    def item(self, name: str) -> Item:
        """The item called ``name`` (KeyError naming it otherwise)."""
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"model {self.name}: no control-table item {name!r}") from None

    def item_at(self, address: int) -> Item | None:
        """The item starting at ``address``, or None."""
        return self._by_address.get(address)

    def address(self, name: str) -> int:
        return self.item(name).address


def _x_series_items(model_number: int, firmware: int, velocity_limit: int, current_limit: int) -> tuple[Item, ...]:
    """Items shared by the XM430/XM540 family (e-manual "Control Table of EEPROM/RAM Area")."""
    items: list[Item] = [
        Item("model_number", 0, 2, "R", model_number),
        Item("model_information", 2, 4, "R", 0),
        Item("firmware_version", 6, 1, "R", firmware),
        Item("id", 7, 1, "RW", 1, 0, 252),
        Item("baud_rate", 8, 1, "RW", 1, allowed=frozenset(BAUD_RATES)),
        Item("return_delay_time", 9, 1, "RW", 250, 0, 254),
        Item("drive_mode", 10, 1, "RW", 0, 0, 13),
        Item("operating_mode", 11, 1, "RW", MODE_POSITION, allowed=frozenset({0, 1, 3, 4, 5, 16})),
        Item("secondary_id", 12, 1, "RW", 255, 0, 255),
        Item("protocol_type", 13, 1, "RW", 2, allowed=frozenset({1, 2})),
        Item("homing_offset", 20, 4, "RW", 0, -1_044_479, 1_044_479, signed=True),
        Item("moving_threshold", 24, 4, "RW", 10, 0, 1023),
        Item("temperature_limit", 31, 1, "RW", 80, 0, 100),
        Item("max_voltage_limit", 32, 2, "RW", 160, 95, 160),
        Item("min_voltage_limit", 34, 2, "RW", 95, 95, 160),
        Item("pwm_limit", 36, 2, "RW", 885, 0, 885),
        Item("current_limit", 38, 2, "RW", current_limit, 0, current_limit),
        Item("velocity_limit", 44, 4, "RW", velocity_limit, 0, 1023),
        Item("max_position_limit", 48, 4, "RW", 4095, 0, 4095),
        Item("min_position_limit", 52, 4, "RW", 0, 0, 4095),
        Item("startup_configuration", 60, 1, "RW", 0, 0, 3),
        Item("shutdown", 63, 1, "RW", 52, 0, 0x3F),
        # RAM
        Item("torque_enable", 64, 1, "RW", 0, 0, 1),
        Item("led", 65, 1, "RW", 0, 0, 1),
        Item("status_return_level", 68, 1, "RW", 2, 0, 2),
        Item("registered_instruction", 69, 1, "R", 0),
        Item("hardware_error_status", 70, 1, "R", 0),
        Item("velocity_i_gain", 76, 2, "RW", 1920, 0, 16383),
        Item("velocity_p_gain", 78, 2, "RW", 100, 0, 16383),
        Item("position_d_gain", 80, 2, "RW", 0, 0, 16383),
        Item("position_i_gain", 82, 2, "RW", 0, 0, 16383),
        Item("position_p_gain", 84, 2, "RW", 800, 0, 16383),
        Item("feedforward_2nd_gain", 88, 2, "RW", 0, 0, 16383),
        Item("feedforward_1st_gain", 90, 2, "RW", 0, 0, 16383),
        Item("bus_watchdog", 98, 1, "RW", 0, 0, 127),
        Item("goal_pwm", 100, 2, "RW", 0, -885, 885, signed=True),
        Item("goal_current", 102, 2, "RW", 0, -current_limit, current_limit, signed=True),
        Item("goal_velocity", 104, 4, "RW", 0, -1023, 1023, signed=True),
        Item("profile_acceleration", 108, 4, "RW", 0, 0, 32767),
        Item("profile_velocity", 112, 4, "RW", 0, 0, 32767),
        Item("goal_position", 116, 4, "RW", 0, -1_048_575, 1_048_575, signed=True),
        Item("realtime_tick", 120, 2, "R", 0),
        Item("moving", 122, 1, "R", 0),
        Item("moving_status", 123, 1, "R", 0),
        Item("present_pwm", 124, 2, "R", 0, signed=True),
        Item("present_current", 126, 2, "R", 0, signed=True),
        Item("present_velocity", 128, 4, "R", 0, signed=True),
        Item("present_position", 132, 4, "R", 0, signed=True),
        Item("velocity_trajectory", 136, 4, "R", 0, signed=True),
        Item("position_trajectory", 140, 4, "R", 0, signed=True),
        Item("present_input_voltage", 144, 2, "R", 120),
        Item("present_temperature", 146, 1, "R", 25),
        Item("backup_ready", 147, 1, "R", 0),
    ]
    for n in range(28):
        items.append(Item(f"indirect_address_{n + 1}", 168 + 2 * n, 2, "RW", 224 + n, 64, 661))
        items.append(Item(f"indirect_data_{n + 1}", 224 + n, 1, "RW", 0))
    for n in range(28):
        items.append(Item(f"indirect_address_{n + 29}", 578 + 2 * n, 2, "RW", 634 + n, 64, 661))
        items.append(Item(f"indirect_data_{n + 29}", 634 + n, 1, "RW", 0))
    return tuple(items)


def xm430_w350() -> ModelSpec:
    """ROBOTIS XM430-W350 (model number 1020)."""
    return ModelSpec("XM430-W350", 1020, 52, _x_series_items(1020, 52, 200, 1193), no_load_speed_rpm=46.0)


def xm430_w210() -> ModelSpec:
    """ROBOTIS XM430-W210 (model number 1030): same table, faster gearing."""
    return ModelSpec("XM430-W210", 1030, 52, _x_series_items(1030, 52, 330, 1193), no_load_speed_rpm=77.0)


#: Emulated models by name; add a factory here to plug in another model.
MODELS: dict[str, Callable[[], ModelSpec]] = {
    "XM430-W350": xm430_w350,
    "XM430-W210": xm430_w210,
}

_CACHE: dict[str, ModelSpec] = {}


def get_model(name: str) -> ModelSpec:
    """The spec of model ``name``; ValueError listing the known models otherwise."""
    spec = _CACHE.get(name)
    if spec is None:
        factory = MODELS.get(name)
        if factory is None:
            raise ValueError(f"unknown Dynamixel model {name!r}; known: {', '.join(sorted(MODELS))}")
        spec = _CACHE[name] = factory()
    return spec


def register_model(name: str, factory: Callable[[], ModelSpec]) -> None:
    """Make another model available to the emulator under ``name``."""
    MODELS[name] = factory
    _CACHE.pop(name, None)


def item_names(spec: ModelSpec) -> Iterable[str]:
    """Names of every item of ``spec`` in address order."""
    return (it.name for it in sorted(spec.items, key=lambda it: it.address))
