"""One emulated Dynamixel servo: control-table memory with the e-manual's access rules, plus a motion model.

The motion model is advanced lazily to the wall-clock time of each access (no ticking thread):
position control follows a trapezoidal profile bounded by Profile Velocity/Acceleration and the
Velocity Limit; velocity mode tracks Goal Velocity; torque off means no drive (the shaft stays
where it is unless :meth:`Servo.set_shaft_position` moves it, as a mechanism would). Hardware
error conditions (overheating, overload, input voltage, electrical shock, encoder) latch bits in
Hardware Error Status, turn torque off when their bit is in Shutdown, and set the status
packets' alert bit until a reboot.
"""

from __future__ import annotations

import math
import struct
import time

from sim_hardware.dynamixel.control_table import (
    MODE_EXTENDED_POSITION,
    MODE_POSITION,
    MODE_VELOCITY,
    ModelSpec,
)
from sim_hardware.dynamixel.protocol import ALERT_BIT, HardwareError, ResultError

AMBIENT_TEMPERATURE_C = 25.0
#: Thermal time constant of the housing (s): an injected overheat cools down at this rate.
THERMAL_TAU_S = 30.0
NOMINAL_VOLTAGE_V = 12.0
#: Longest integration sub-step (s) of the motion model.
MAX_SUBSTEP_S = 0.002

_POSITION_MODES = (MODE_POSITION, MODE_EXTENDED_POSITION, 5)
_HOMING_THRESHOLD = struct.Struct("<iI")
_U16 = struct.Struct("<H")
_VOLTAGE_LIMITS = struct.Struct("<HH")
_I32 = struct.Struct("<i")
#: realtime tick .. present temperature (addresses 120–146)
_PRESENT = struct.Struct("<HBBhhiiiiHB")


class Servo:
    """Control table + motion state of one servo; not thread-safe (the emulator serialises access)."""

    def __init__(self, model: ModelSpec, device_id: int, *, initial_position: int = 0,
                 clock=time.monotonic) -> None:
        self.model = model
        self._clock = clock
        self.memory = bytearray(model.size)
        self._items = model.items
        self._addr = {it.name: it.address for it in model.items}
        self._indirect: list[tuple[int, int, int]] = list(model.indirect_address_blocks)
        self._translations: dict[tuple[int, int], list[int]] = {}  # (address, length) -> real addresses
        self._owner: list = [None] * model.size  # byte address -> item containing it
        for it in model.items:
            for b in range(it.address, it.address + it.size):
                self._owner[b] = it
        self._refreshed_at = -1.0
        self._load_defaults(eeprom=True)
        self.write_item("id", device_id)
        # physical state (shaft frame, encoder counts; reported position = shaft + homing offset)
        self.shaft = float(initial_position)
        self.velocity = 0.0  # counts/s
        self.acceleration = 0.0  # counts/s²
        self.temperature = AMBIENT_TEMPERATURE_C
        self.voltage = NOMINAL_VOLTAGE_V
        self.overload_condition = False
        self.latched_errors = 0  # errors that only a reboot clears (electrical shock, encoder)
        self.registered: tuple[int, bytes] | None = None
        self.boot_time = clock()
        self.unresponsive_until = 0.0
        self._last = self.boot_time
        self._vel_unit = model.velocity_unit_rpm * model.counts_per_rev / 60.0  # counts/s per unit
        self._acc_unit = model.acceleration_unit_rpm2 * model.counts_per_rev / 3600.0  # counts/s² per unit
        self._pwm_per_unit = 885 * model.velocity_unit_rpm / model.no_load_speed_rpm
        self._after_boot()

    # ------------------------------------------------------------------ memory helpers
    def _load_defaults(self, *, eeprom: bool, keep: tuple[str, ...] = ()) -> None:
        kept = {name: self.read_item(name) for name in keep}
        for it in self._items:
            if it.eeprom == eeprom or (eeprom and not it.eeprom):
                self._store(it.address, it.size, it.default, it.signed)
        for name, value in kept.items():
            self.write_item(name, value)

    def _store(self, address: int, size: int, value: int, signed: bool = False) -> None:
        self.memory[address:address + size] = value.to_bytes(size, "little", signed=signed and value < 0)
        for addr_base, _, count in self._indirect:
            if addr_base <= address < addr_base + 2 * count:
                self._translations.clear()

    def read_item(self, name: str) -> int:
        """Current value of an item (no motion update)."""
        it = self.model.item(name)
        return int.from_bytes(self.memory[it.address:it.address + it.size], "little", signed=it.signed)

    def write_item(self, name: str, value: int) -> None:
        """Set an item directly, bypassing access checks (emulator/test use)."""
        it = self.model.item(name)
        self._store(it.address, it.size, int(value), it.signed)

    def _u(self, address: int, size: int) -> int:
        return int.from_bytes(self.memory[address:address + size], "little")

    def _s(self, address: int, size: int) -> int:
        return int.from_bytes(self.memory[address:address + size], "little", signed=True)

    @property
    def device_id(self) -> int:
        return self.memory[7]

    @property
    def torque_enabled(self) -> bool:
        return self.memory[64] == 1

    @property
    def hardware_error(self) -> int:
        return self.memory[70]

    @property
    def status_return_level(self) -> int:
        return self.memory[68]

    @property
    def return_delay_s(self) -> float:
        return self.memory[9] * 2e-6

    @property
    def alert(self) -> int:
        """ALERT_BIT when a hardware error is latched, else 0 (OR it into every status error byte)."""
        return ALERT_BIT if self.memory[70] else 0

    # ------------------------------------------------------------------ motion model
    def _after_boot(self) -> None:
        now = self._clock()
        self.boot_time = now
        self._last = now
        self.velocity = 0.0
        self.acceleration = 0.0
        self._store(116, 4, self.reported_position(), True)
        self._check_errors()
        self._refresh(now)

    def reported_position(self) -> int:
        """Present Position in counts (shaft + homing offset)."""
        return round(self.shaft) + self._s(20, 4)

    def set_shaft_position(self, counts: float) -> None:
        """Move the shaft from outside (a mechanism back-driving a torque-off servo, or a test)."""
        self.shaft = float(counts)
        self.velocity = 0.0
        self._refreshed_at = -1.0

    def advance(self, now: float | None = None, *, refresh: bool = True) -> None:
        """Integrate the motion and thermal model up to ``now``; refresh the present-value items if asked."""
        if now is None:
            now = self._clock()
        dt = now - self._last
        if dt > 0:
            self._last = now
            self._integrate(dt)
            if self.temperature > AMBIENT_TEMPERATURE_C:
                self.temperature = AMBIENT_TEMPERATURE_C + (self.temperature - AMBIENT_TEMPERATURE_C) * math.exp(
                    -dt / THERMAL_TAU_S)
        self._check_errors()
        if refresh and now != self._refreshed_at:
            self._refresh(now)

    def _profile_limits(self) -> tuple[float, float]:
        mem = self.memory
        vel_limit = int.from_bytes(mem[44:48], "little") * self._vel_unit
        no_load = self.model.no_load_speed_rpm * self.model.counts_per_rev / 60.0
        vmax = min(no_load, vel_limit) if vel_limit > 0 else no_load
        pv = int.from_bytes(mem[112:116], "little")
        if pv:
            vmax = min(vmax, pv * self._vel_unit)
        pa = int.from_bytes(mem[108:112], "little")
        amax = pa * self._acc_unit if pa else math.inf
        return vmax, amax

    def _integrate(self, dt: float) -> None:
        if not self.torque_enabled:
            self.velocity = 0.0
            self.acceleration = 0.0
            return
        mode = self.memory[11]
        if mode in _POSITION_MODES:
            target = _I32.unpack_from(self.memory, 116)[0] - _I32.unpack_from(self.memory, 20)[0]
            p, v = self.shaft, self.velocity
            if v == 0.0 and p == target:  # settled: nothing to integrate
                self.acceleration = 0.0
                return
            vmax, amax = self._profile_limits()
            remaining = dt
            v0 = v
            while remaining > 0:
                err = target - p
                if abs(err) < 0.5 and abs(v) < 1e-6:
                    p, v = float(target), 0.0
                    break
                h = min(remaining, MAX_SUBSTEP_S)
                remaining -= h
                speed = vmax if amax == math.inf else min(vmax, math.sqrt(2.0 * amax * abs(err)))
                v_des = math.copysign(speed, err)
                if amax == math.inf:
                    v = v_des
                else:
                    dv = v_des - v
                    lim = amax * h
                    v += max(-lim, min(lim, dv))
                p_new = p + v * h
                if (target - p_new) * err <= 0:  # reached or crossed the goal
                    p, v = float(target), 0.0
                    break
                p = p_new
            self.acceleration = (v - v0) / dt
            self.shaft, self.velocity = p, v
        elif mode == MODE_VELOCITY:
            vmax, amax = self._profile_limits()
            goal = self._s(104, 4) * self._vel_unit
            v0 = self.velocity
            if amax == math.inf:
                v = goal
                self.shaft += v * dt
            else:
                t_ramp = min(dt, abs(goal - v0) / amax)
                v = v0 + math.copysign(amax * t_ramp, goal - v0)
                self.shaft += 0.5 * (v0 + v) * t_ramp + v * (dt - t_ramp)
            self.velocity = v
            self.acceleration = (v - v0) / dt
        else:  # current and PWM modes: no load model, the shaft stays put
            self.velocity = 0.0
            self.acceleration = 0.0

    def _check_errors(self) -> None:
        bits = self.latched_errors
        if self.temperature > self.memory[31]:
            bits |= HardwareError.OVERHEATING
        volts = self.voltage * 10.0
        high, low = _VOLTAGE_LIMITS.unpack_from(self.memory, 32)
        if volts < low or volts > high:
            bits |= HardwareError.INPUT_VOLTAGE
        if self.overload_condition:
            bits |= HardwareError.OVERLOAD
        if bits:
            new = self.memory[70] | bits
            self.memory[70] = new
            if new & self.memory[63] and self.torque_enabled:
                self.memory[64] = 0
                self.velocity = 0.0
                self.acceleration = 0.0

    def _refresh(self, now: float) -> None:
        """Write the present-value items from the physical state."""
        mem = self.memory
        self._refreshed_at = now
        homing, threshold = _HOMING_THRESHOLD.unpack_from(mem, 20)
        current_limit = _U16.unpack_from(mem, 38)[0]
        goal = _I32.unpack_from(mem, 116)[0]
        torque = mem[64] == 1
        position_mode = mem[11] in _POSITION_MODES
        vel_units = round(self.velocity / self._vel_unit)
        if self.overload_condition and torque:
            current = current_limit
        else:
            current = round(0.004 * self.acceleration + 0.05 * vel_units)
            current = max(-current_limit, min(current_limit, current))
        pwm = round(vel_units * self._pwm_per_unit) if torque else 0
        pos = round(self.shaft) + homing
        status = 0
        if torque:
            status = 0x30  # trapezoidal profile
            if position_mode:
                if abs(goal - pos) <= threshold:
                    status |= 0x01  # in position
                if self.velocity != 0.0:
                    status |= 0x02  # profile ongoing
        _PRESENT.pack_into(mem, 120, int((now - self.boot_time) * 1000) % 32768,
                           1 if abs(vel_units) > threshold else 0, status, pwm, current, vel_units, pos,
                           vel_units, goal if torque and position_mode else pos,
                           round(self.voltage * 10), min(255, max(0, round(self.temperature))))

    # ------------------------------------------------------------------ instructions
    def _translate(self, address: int, length: int) -> list[int] | None:
        """Map ``length`` bytes from ``address`` through indirect data to real addresses (None: out of table)."""
        key = (address, length)
        cached = self._translations.get(key)
        if cached is not None:
            return cached
        if address < 0 or length < 0 or address + length > len(self.memory):
            return None
        out = list(range(address, address + length))
        mem = self.memory
        for addr_base, data_base, count in self._indirect:
            lo, hi = max(address, data_base), min(address + length, data_base + count)
            for a in range(lo, hi):
                k = addr_base + 2 * (a - data_base)
                out[a - address] = mem[k] | (mem[k + 1] << 8)
        if len(self._translations) > 256:
            self._translations.clear()
        self._translations[key] = out
        return out

    def read(self, address: int, length: int, now: float | None = None) -> tuple[int, bytes]:
        """READ: (error byte, data). Unused gaps read as zero; indirect data reads its target."""
        if length == 0 or address + length > len(self.memory) or address < 0:
            return ResultError.ACCESS | self.alert, b""
        self.advance(now)
        mem = self.memory
        data = bytes(mem[address:address + length])
        for _, data_base, count in self._indirect:
            if address < data_base + count and data_base < address + length:
                addrs = self._translate(address, length)
                assert addrs is not None
                data = bytes(mem[a] for a in addrs)
                break
        return self.alert, data

    def write(self, address: int, data: bytes, *, apply: bool = True, now: float | None = None) -> int:
        """WRITE: check every touched item (access, EEPROM lock, length, range, limit); apply all or none.

        Returns the status error byte (result code | alert). With ``apply`` False only checks.
        """
        it = self._owner[address] if 0 <= address < len(self._owner) else None
        if it is not None and it.address == address and it.size == len(data) and not it.name.startswith("indirect"):
            # the common case: exactly one whole item
            self.advance(now, refresh=False)
            error = self._check_item(it, int.from_bytes(data, "little", signed=it.signed))
            if error or not apply:
                return error | self.alert
            self._apply(it, int.from_bytes(data, "little", signed=it.signed))
            self._refreshed_at = -1.0
            return self.alert
        addrs = self._translate(address, len(data))
        if addrs is None or not data:
            return ResultError.ACCESS | self.alert
        self.advance(now, refresh=False)
        staged = dict(zip(addrs, data, strict=True))
        updates: list[tuple[object, int]] = []
        seen: set[int] = set()
        for a in addrs:
            if a in seen:
                continue
            it = self._owner[a]
            if it is None:
                return ResultError.ACCESS | self.alert
            span = range(it.address, it.address + it.size)
            if any(b not in staged for b in span):
                return ResultError.DATA_LENGTH | self.alert
            seen.update(span)
            value = int.from_bytes(bytes(staged[b] for b in span), "little", signed=it.signed)
            error = self._check_item(it, value)
            if error:
                return error | self.alert
            updates.append((it, value))
        if not apply:
            return self.alert
        for it, value in updates:
            self._apply(it, value)  # type: ignore[arg-type]
        self._refreshed_at = -1.0
        return self.alert

    def _check_item(self, it, value: int) -> int:
        """Result error of writing ``value`` to item ``it`` now (0 when allowed)."""
        if not it.writable:
            return ResultError.ACCESS
        if (it.eeprom or it.name.startswith("indirect_address")) and self.memory[64] == 1:
            return ResultError.ACCESS
        if it.allowed is not None and value not in it.allowed:
            return ResultError.DATA_RANGE
        if (it.low is not None and value < it.low) or (it.high is not None and value > it.high):
            return ResultError.DATA_RANGE
        return self._limit_check(it.name, value)

    def _limit_check(self, name: str, value: int) -> int:
        mem = self.memory
        if name == "goal_position" and mem[11] == MODE_POSITION:
            if not self._s(52, 4) <= value <= self._s(48, 4):
                return ResultError.DATA_LIMIT
        elif name == "goal_velocity":
            if abs(value) > self._u(44, 4):
                return ResultError.DATA_LIMIT
        elif name == "goal_current":
            if abs(value) > self._u(38, 2):
                return ResultError.DATA_LIMIT
        elif name == "goal_pwm":
            if abs(value) > self._u(36, 2):
                return ResultError.DATA_LIMIT
        elif name == "torque_enable" and value == 1 and mem[70]:
            return ResultError.RESULT_FAIL  # no torque until a reboot clears the hardware error
        return 0

    def _apply(self, it, value: int) -> None:
        if it.name == "torque_enable" and value == 0:
            self.velocity = 0.0
            self.acceleration = 0.0
        self._store(it.address, it.size, value, it.signed)

    def reg_write(self, address: int, data: bytes) -> int:
        """REG WRITE: validate now, hold the write until ACTION."""
        error = self.write(address, data, apply=False)
        if error & 0x7F:
            return error
        self.registered = (address, bytes(data))
        self.memory[69] = 1
        return self.alert

    def action(self) -> int:
        """ACTION: perform the registered write (instruction error when none is registered)."""
        if self.registered is None:
            return ResultError.INSTRUCTION | self.alert
        address, data = self.registered
        self.registered = None
        self.memory[69] = 0
        return self.write(address, data)

    def reboot(self, reboot_time_s: float) -> None:
        """REBOOT: clear errors, reload RAM defaults, stay silent for ``reboot_time_s``."""
        self.advance()
        self.latched_errors = 0
        self.registered = None
        self._load_defaults(eeprom=False)
        self.unresponsive_until = self._clock() + reboot_time_s
        self._after_boot()

    def factory_reset(self, option: int) -> int:
        """FACTORY RESET: 0xFF everything, 0x01 all but ID, 0x02 all but ID and baud rate."""
        if option not in (0x01, 0x02, 0xFF):
            return ResultError.DATA_RANGE | self.alert
        if self.torque_enabled:
            return ResultError.ACCESS | self.alert
        keep = {0x01: ("id",), 0x02: ("id", "baud_rate"), 0xFF: ()}[option]
        self._load_defaults(eeprom=True, keep=keep)
        self._load_defaults(eeprom=False)
        self._after_boot()
        return self.alert

    def ping_params(self) -> bytes:
        """PING status params: model number (LE16) and firmware version."""
        return bytes(self.memory[0:2]) + bytes((self.memory[6],))

    # ------------------------------------------------------------------ ground truth for tests and mechanisms
    def position_rad(self) -> float:
        """Shaft angle (rad) from count 0, the ground truth a mechanism would see."""
        return self.shaft * 2.0 * math.pi / self.model.counts_per_rev
