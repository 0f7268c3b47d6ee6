"""``DynamixelBus``: X-series Dynamixel servos over protocol 2.0 through the official dynamixel-sdk.

Open pings every configured id (a silent id raises :class:`BusTimeout` naming it), checks the
model number, turns torque off and configures each servo (operating mode, return delay time,
position limits, profile velocity and acceleration, and an indirect-address block so one sync read returns
hardware error, torque, current, velocity and position). Each cycle is one ``GroupSyncWrite``
of goal positions and one ``GroupSyncRead`` (fast sync read where the model supports it).
A hardware error bit puts the bus in FAULT with the bits as code; ``reset_fault`` reboots the
faulted servos and configures them again. A read that gets no answer returns the previous
states (their timestamps show their age) until ``max_consecutive_failures`` reads in a row
failed; then the bus faults and raises :class:`BusTimeout`. The SDK is not thread-safe, so
every port access holds one lock. A ``port`` of "auto" (simulated buses in a head file) must be
replaced by the caller with the emulator's device path before opening.

Options: ``port`` (device path), ``baudrate`` (default 1000000), ``protocol`` (2.0 only),
``model`` (default "XM430-W350"), ``return_delay_us`` (0–508, even; default 0),
``use_fast_sync_read`` ("auto" by model, or a bool), ``operating_mode`` ("auto", "position",
"extended_position"), ``max_consecutive_failures`` (default 3), ``retries`` (extra tries of a ping or configuration
transaction that got no answer; default 2),
``reboot_timeout_s`` (default 2.0).
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn, TypeVar

from drivers.base import LifecycleState, MotorBus, MotorConfig, MotorState
from drivers.errors import BusConnectionLost, BusInitError, BusTimeout, CommandRejected, ConfigError, DeviceFault

log = logging.getLogger(__name__)

#: Longest a serial read blocks before the SDK looks at its packet timeout again (s).
READ_BLOCK_S = 0.002
T = TypeVar("T")

# X-series control table addresses (protocol 2.0)
ADDR_MODEL_NUMBER = 0
ADDR_RETURN_DELAY = 9
ADDR_OPERATING_MODE = 11
ADDR_VELOCITY_LIMIT = 44
ADDR_MAX_POSITION_LIMIT = 48
ADDR_MIN_POSITION_LIMIT = 52
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_PROFILE_ACCELERATION = 108
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_CURRENT = 126
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
ADDR_INDIRECT_ADDRESS_1 = 168
ADDR_INDIRECT_DATA_1 = 224

MODE_POSITION = 3
MODE_EXTENDED_POSITION = 4

#: Bytes mapped into the indirect data block, in order: hardware error, torque, current, velocity, position.
INDIRECT_LAYOUT: tuple[int, ...] = (
    ADDR_HARDWARE_ERROR,
    ADDR_TORQUE_ENABLE,
    *range(ADDR_PRESENT_CURRENT, ADDR_PRESENT_CURRENT + 2),
    *range(ADDR_PRESENT_VELOCITY, ADDR_PRESENT_VELOCITY + 4),
    *range(ADDR_PRESENT_POSITION, ADDR_PRESENT_POSITION + 4),
)
_STATE = struct.Struct("<BBhii")

#: Fault codes of this driver beyond the servo's hardware-error bits (which are 0x01–0x3F).
FAULT_TORQUE_LOST = 0x0100
FAULT_COMMUNICATION = 0x0200

HARDWARE_ERROR_NAMES = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}
RESULT_ERROR_NAMES = {
    1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error",
    5: "data length error", 6: "data limit error", 7: "access error",
}
#: Longest status packet dynamixel-sdk accepts (its RXPACKET_MAX_LEN).
SDK_MAX_PACKET = 1024
SUPPORTED_BAUDRATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)
_OPTIONS = {
    "port", "baudrate", "protocol", "model", "return_delay_us", "use_fast_sync_read", "operating_mode",
    "max_consecutive_failures", "retries", "reboot_timeout_s",
}


@dataclass(frozen=True, slots=True)
class ServoModel:
    """What the driver needs to know about a servo model: its model number and unit scales."""

    name: str
    number: int
    velocity_unit_rpm: float = 0.229
    current_unit_a: float = 2.69e-3
    position_range: tuple[int, int] = (0, 4095)
    fast_sync_read: bool = True


#: Supported models by name (X series sharing the XM430 control-table layout).
SERVO_MODELS: dict[str, ServoModel] = {
    m.name: m
    for m in (
        ServoModel("XM430-W350", 1020),
        ServoModel("XM430-W210", 1030),
        ServoModel("XM540-W270", 1120),
        ServoModel("XM540-W150", 1130),
    )
}


def describe_hardware_error(bits: int) -> str:
    """Human-readable names of hardware error bits."""
    names = [name for bit, name in HARDWARE_ERROR_NAMES.items() if bits & bit]
    return ", ".join(names) or f"unknown bits 0x{bits:02X}"


class DynamixelBus(MotorBus):
    """X-series Dynamixel servos on one serial port (protocol 2.0)."""

    driver_name = "dynamixel"

    def __init__(self, name: str, options: Mapping[str, Any], motors: Sequence[MotorConfig]) -> None:
        super().__init__(name, options, motors)
        opts = self.options
        unknown = sorted(set(opts) - _OPTIONS)
        if unknown:
            raise ConfigError(f"bus {name!r}.options", f"unknown option(s) {', '.join(unknown)}; "
                                                        f"known: {', '.join(sorted(_OPTIONS))}")
        self._port_name = self._opt_str("port", None)
        self._baudrate = self._opt_int("baudrate", 1_000_000)
        if self._baudrate not in SUPPORTED_BAUDRATES:
            raise ConfigError(f"bus {name!r}.options.baudrate",
                              f"{self._baudrate!r} not supported; use one of {SUPPORTED_BAUDRATES}")
        protocol = opts.get("protocol", 2.0)
        if isinstance(protocol, bool) or str(protocol) not in ("2", "2.0"):
            raise ConfigError(f"bus {name!r}.options.protocol", f"only protocol 2.0 is supported, got {protocol!r}")
        model_name = self._opt_str("model", "XM430-W350")
        if model_name not in SERVO_MODELS:
            raise ConfigError(f"bus {name!r}.options.model",
                              f"unknown model {model_name!r}; supported: {', '.join(sorted(SERVO_MODELS))}")
        self.model = SERVO_MODELS[model_name]
        self._return_delay_us = self._opt_int("return_delay_us", 0)
        if not 0 <= self._return_delay_us <= 508 or self._return_delay_us % 2:
            raise ConfigError(f"bus {name!r}.options.return_delay_us",
                              f"must be an even number of microseconds in 0..508, got {self._return_delay_us!r}")
        fast = opts.get("use_fast_sync_read", "auto")
        # the answer to a fast sync read is one packet; the SDK takes packets up to 1 KiB
        fits = 8 + len(self.motors) * (len(INDIRECT_LAYOUT) + 4) <= SDK_MAX_PACKET
        if fast == "auto":
            self._fast = self.model.fast_sync_read and fits
        elif isinstance(fast, bool):
            if fast and not fits:
                raise ConfigError(f"bus {name!r}.options.use_fast_sync_read",
                                  f"the answer for {len(self.motors)} servos exceeds the SDK's {SDK_MAX_PACKET}-byte "
                                  "packet; use a normal sync read ('auto' or false)")
            self._fast = fast
        else:
            raise ConfigError(f"bus {name!r}.options.use_fast_sync_read",
                              f"must be 'auto', true or false, got {fast!r}")
        self._max_failures = self._opt_int("max_consecutive_failures", 3)
        if self._max_failures < 1:
            raise ConfigError(f"bus {name!r}.options.max_consecutive_failures",
                              f"must be at least 1, got {self._max_failures!r}")
        self._retries = self._opt_int("retries", 2)
        if not 0 <= self._retries <= 10:
            raise ConfigError(f"bus {name!r}.options.retries", f"must be in 0..10, got {self._retries!r}")
        self._reboot_timeout = opts.get("reboot_timeout_s", 2.0)
        if isinstance(self._reboot_timeout, bool) or not isinstance(self._reboot_timeout, (int, float)) \
                or not 0 < self._reboot_timeout <= 60:
            raise ConfigError(f"bus {name!r}.options.reboot_timeout_s",
                              f"must be a number of seconds in (0, 60], got {self._reboot_timeout!r}")
        for motor in self.motors.values():
            if not 0 <= motor.device_id <= 252:
                raise ConfigError(f"motor {motor.name!r}.device_id", f"must be in 0..252, got {motor.device_id}")
        self._ranges = {m.name: self._count_range(m) for m in self.motors.values()}
        self._mode = self._choose_mode(opts.get("operating_mode", "auto"))
        self._by_id = {m.device_id: m for m in self.motors.values()}
        self._ids = sorted(self._by_id)
        self._io = threading.Lock()
        self._port: Any = None
        self._ph: Any = None
        self._sync_read: Any = None
        self._sync_write: Any = None
        self._failures = 0
        self._last_states: dict[str, MotorState] = {}
        self._last_raw: dict[int, tuple[int, int, int, int, int]] = {}
        self._enabling = False  # set between _enable and the read MotorBus.enable makes right after it

    # ------------------------------------------------------------------ option helpers
    def _opt_str(self, key: str, default: str | None) -> str:
        value = self.options.get(key, default)
        if not isinstance(value, str) or not value:
            raise ConfigError(f"bus {self.name!r}.options.{key}", f"must be a non-empty string, got {value!r}")
        return value

    def _opt_int(self, key: str, default: int) -> int:
        value = self.options.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"bus {self.name!r}.options.{key}", f"must be an integer, got {value!r}")
        return value

    def _count_range(self, motor: MotorConfig) -> tuple[int, int]:
        a, b = motor.to_counts(motor.min_position), motor.to_counts(motor.max_position)
        return (a, b) if a <= b else (b, a)

    def _choose_mode(self, mode: Any) -> int:
        lo, hi = self.model.position_range
        outside = [n for n, (a, b) in self._ranges.items() if a < lo or b > hi]
        if mode == "auto":
            return MODE_EXTENDED_POSITION if outside else MODE_POSITION
        if mode == "extended_position":
            return MODE_EXTENDED_POSITION
        if mode == "position":
            if outside:
                name = outside[0]
                a, b = self._ranges[name]
                raise ConfigError(
                    f"motor {name!r}",
                    f"range {a}..{b} counts lies outside position mode's {lo}..{hi}; set zero_count so the range "
                    f"fits, or operating_mode = 'extended_position'",
                )
            return MODE_POSITION
        raise ConfigError(f"bus {self.name!r}.options.operating_mode",
                          f"must be 'auto', 'position' or 'extended_position', got {mode!r}")

    @property
    def operating_mode(self) -> int:
        """The operating mode written at open (3 position, 4 extended position)."""
        return self._mode

    @property
    def uses_fast_sync_read(self) -> bool:
        return self._fast

    # ------------------------------------------------------------------ SDK access
    def _device(self, device_id: int) -> str:
        """The name errors and faults use for ``device_id``: its motor name."""
        motor = self._by_id.get(device_id)
        return motor.name if motor else f"id {device_id}"

    def _label(self, device_id: int) -> str:
        motor = self._by_id.get(device_id)
        return f"{motor.name} (id {device_id})" if motor else f"id {device_id}"

    def _call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run one SDK transaction under the port lock; serial exceptions become BusTimeout-able results.

        A transaction the SDK aborts with an exception (a pseudo-terminal closing under it) leaves its port's busy
        flag set, and every later one would answer "Port is in use!" without touching the port, so a lost port would
        never show; the lock here already keeps transactions apart, so the flag is cleared."""
        with self._io:
            try:
                return fn(*args)
            except BaseException:
                if self._port is not None:
                    self._port.is_using = False
                raise

    def _txrx(self, what: str, device_id: int, fn: Callable[..., Any], *args: Any,
              allow_alert: bool = True, retries: int | None = None) -> Any:
        """One acknowledged transaction; raise BusTimeout on no answer, BusInitError on a result error."""
        from dynamixel_sdk import COMM_SUCCESS

        tries = 1 + (self._retries if retries is None else retries)
        for attempt in range(tries):
            try:
                out = self._call(fn, self._port, device_id, *args)
            except (OSError, ValueError, IndexError) as exc:
                raise BusTimeout(self._device(device_id), f"id {device_id}: {what}: port failure: {exc}") from exc
            if isinstance(out, tuple) and len(out) == 3:
                value, result, error = out
            else:
                (result, error), value = out, None
            if result == COMM_SUCCESS:
                break
            log.debug("bus %s: %s: %s (try %d)", self.name, what, self._ph.getTxRxResult(result), attempt + 1)
        else:
            raise BusTimeout(self._device(device_id),
                             f"id {device_id}: {what}: {self._ph.getTxRxResult(result)} ({tries} tries)")
        code = error & 0x7F
        if code:
            raise BusInitError(f"bus {self.name!r}: {self._label(device_id)}: {what} refused: "
                               f"{RESULT_ERROR_NAMES.get(code, f'error {code}')}")
        if error & 0x80 and not allow_alert:
            raise DeviceFault(self._device(device_id), 0, f"{what}: device reports a hardware error")
        return value

    def _write_value(self, device_id: int, address: int, size: int, value: int, what: str) -> None:
        ph = self._ph
        fn = {1: ph.write1ByteTxRx, 2: ph.write2ByteTxRx, 4: ph.write4ByteTxRx}[size]
        self._txrx(what, device_id, fn, address, value & ((1 << (8 * size)) - 1))

    def _read_value(self, device_id: int, address: int, size: int, what: str, signed: bool = False) -> int:
        ph = self._ph
        fn = {1: ph.read1ByteTxRx, 2: ph.read2ByteTxRx, 4: ph.read4ByteTxRx}[size]
        value = int(self._txrx(what, device_id, fn, address))
        if signed and value >= 1 << (8 * size - 1):
            value -= 1 << (8 * size)
        return value

    def _ping(self, device_id: int, attempts: int) -> int | None:
        """Model number of ``device_id``, or None if it never answered."""
        from dynamixel_sdk import COMM_SUCCESS

        for _ in range(attempts):
            try:
                number, result, _error = self._call(self._ph.ping, self._port, device_id)
            except (OSError, ValueError, IndexError):
                return None
            if result == COMM_SUCCESS:
                return int(number)
        return None

    # ------------------------------------------------------------------ lifecycle hooks
    def _open(self) -> None:
        import serial
        from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

        if self._port_name == "auto":
            raise ConfigError(f"bus {self.name!r}.options.port",
                              "'auto' must be replaced by the device path (the emulator's pty when simulated)")
        port = PortHandler(self._port_name)
        try:
            if not port.openPort():
                raise BusInitError(f"bus {self.name!r}: cannot open port {self._port_name!r}")
            if not port.setBaudRate(self._baudrate):
                raise BusInitError(f"bus {self.name!r}: port {self._port_name!r} refused baud rate {self._baudrate}")
            # The SDK polls a non-blocking port in a loop while it waits for a reply (a core spun per transaction);
            # a short blocking read lets the kernel wake us when the bytes are there, at the same packet timeouts.
            port.ser.timeout = READ_BLOCK_S
        except (serial.SerialException, OSError) as exc:
            raise BusInitError(f"bus {self.name!r}: cannot open port {self._port_name!r}: {exc}") from exc
        self._port, self._ph = port, PacketHandler(2.0)
        try:
            for device_id in self._ids:
                self._identify(device_id)
            for device_id in self._ids:
                self._configure(device_id)
            self._sync_read = GroupSyncRead(port, self._ph, ADDR_INDIRECT_DATA_1, len(INDIRECT_LAYOUT))
            self._sync_write = GroupSyncWrite(port, self._ph, ADDR_GOAL_POSITION, 4)
            for device_id in self._ids:
                self._sync_read.addParam(device_id)
            self._failures = 0
            self._last_states = {}
        except BaseException:
            self._close()
            raise

    def _identify(self, device_id: int) -> None:
        number = self._ping(device_id, 1 + self._retries)
        if number is None:
            raise BusTimeout(self._device(device_id),
                             f"id {device_id}: no answer to ping on {self._port_name} ({1 + self._retries} tries)")
        if number != self.model.number:
            raise BusInitError(f"bus {self.name!r}: {self._label(device_id)} is model number {number}, "
                               f"configured model {self.model.name} is {self.model.number}")

    def _configure(self, device_id: int) -> None:
        """Torque off, then EEPROM settings (only when they differ, to spare the EEPROM), then RAM settings."""
        motor = self._by_id[device_id]
        self._write_value(device_id, ADDR_TORQUE_ENABLE, 1, 0, "torque off")
        if self._read_value(device_id, ADDR_OPERATING_MODE, 1, "read operating mode") != self._mode:
            self._write_value(device_id, ADDR_OPERATING_MODE, 1, self._mode, "set operating mode")
        delay = self._return_delay_us // 2
        if self._read_value(device_id, ADDR_RETURN_DELAY, 1, "read return delay") != delay:
            self._write_value(device_id, ADDR_RETURN_DELAY, 1, delay, "set return delay")
        if self._mode == MODE_POSITION:
            lo, hi = self._ranges[motor.name]
            if self._read_value(device_id, ADDR_MAX_POSITION_LIMIT, 4, "read max position limit") != hi:
                self._write_value(device_id, ADDR_MAX_POSITION_LIMIT, 4, hi, "set max position limit")
            if self._read_value(device_id, ADDR_MIN_POSITION_LIMIT, 4, "read min position limit") != lo:
                self._write_value(device_id, ADDR_MIN_POSITION_LIMIT, 4, lo, "set min position limit")
        layout = b"".join(a.to_bytes(2, "little") for a in INDIRECT_LAYOUT)
        self._txrx("map indirect addresses", device_id, self._ph.writeTxRx, ADDR_INDIRECT_ADDRESS_1,
                   len(layout), list(layout))
        # Motion is shaped once, upstream (runtime.shaper); the servo only caps speed in hardware. Profile velocity is
        # the configured max velocity (rounded up to whole units, within the servo's velocity limit), which the
        # shaped commands stay below, so it never shapes normal motion; it still holds if a goal ever jumps (a fault,
        # a reboot, a write around the rate guard), where "0 = unlimited" would leave only the position limits and
        # let the servo slam at full speed. Profile acceleration 0: no acceleration ramp of the servo's own.
        velocity_limit = self._read_value(device_id, ADDR_VELOCITY_LIMIT, 4, "read velocity limit")
        units = math.ceil(abs(motor.velocity_to_counts(motor.max_velocity)) / self._velocity_unit_counts - 1e-9)
        units = max(1, min(units, velocity_limit)) if velocity_limit else max(1, units)
        self._write_value(device_id, ADDR_PROFILE_ACCELERATION, 4, 0, "set profile acceleration")
        self._write_value(device_id, ADDR_PROFILE_VELOCITY, 4, units, "set profile velocity")

    @property
    def _velocity_unit_counts(self) -> float:
        """Encoder counts per second in one velocity unit (0.229 rpm on X series)."""
        return self.model.velocity_unit_rpm * 4096 / 60.0

    def _close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                with self._io:
                    port.closePort()
            except Exception as exc:  # an already broken port must not mask the caller's error
                log.debug("bus %s: closing port failed: %s", self.name, exc)
        self._sync_read = self._sync_write = None

    def _enable(self) -> None:
        states = self._read()
        if self._state is LifecycleState.FAULT:
            device, (code, message) = next(iter(self._faults.items()))
            raise DeviceFault(device, code, f"cannot enable: {message}")
        raw = self._last_raw
        for name, state in states.items():
            motor = self.motors[name]
            lo, hi = self._ranges[name]
            counts = raw[motor.device_id][4]
            if not lo - 2 <= counts <= hi + 2:
                raise CommandRejected(
                    f"{name}: present position {state.position:.4g} ({counts} counts) is outside "
                    f"[{motor.min_position:.4g}, {motor.max_position:.4g}]; move it into range with torque off"
                )
        try:  # acknowledged writes, so a servo refusing torque (hardware error) is known at once
            for device_id in self._ids:
                counts = raw[device_id][4]
                lo, hi = self._ranges[self._by_id[device_id].name]
                self._write_value(device_id, ADDR_GOAL_POSITION, 4, min(max(counts, lo), hi), "hold position")
                self._write_value(device_id, ADDR_TORQUE_ENABLE, 1, 1, "torque on")
        except Exception:
            self._torque_off_all()
            raise
        self._enabling = True

    def _disable(self) -> None:
        self._torque_off_all()

    def _torque_off_all(self) -> None:
        """Broadcast torque off to every configured servo (a sync write: no answer to wait for)."""
        if self._port is None:
            return
        from dynamixel_sdk import GroupSyncWrite

        group = GroupSyncWrite(self._port, self._ph, ADDR_TORQUE_ENABLE, 1)
        for device_id in self._ids:
            group.addParam(device_id, [0])
        try:
            self._call(group.txPacket)
        except (OSError, ValueError) as exc:
            log.error("bus %s: torque off failed: %s", self.name, exc)

    def _write(self, targets: Mapping[str, float]) -> None:
        from dynamixel_sdk import COMM_SUCCESS

        group = self._sync_write
        group.clearParam()
        for name, target in targets.items():
            motor = self.motors[name]
            lo, hi = self._ranges[name]
            counts = min(max(motor.to_counts(target), lo), hi)
            group.addParam(motor.device_id, (counts & 0xFFFFFFFF).to_bytes(4, "little"))
        if not targets:
            return
        try:
            result = self._call(group.txPacket)
        except OSError as exc:
            self._port_lost("sync write", exc)
        except ValueError as exc:
            result = None
            log.warning("bus %s: sync write failed: %s", self.name, exc)
        if result != COMM_SUCCESS:
            self._communication_failure(self.name, "sync write of goal positions failed")

    def _read(self) -> dict[str, MotorState]:
        from dynamixel_sdk import COMM_SUCCESS

        enabling, self._enabling = self._enabling, False
        group = self._sync_read
        for device_id in self._ids:
            group.data_dict[device_id] = []
        try:
            result = self._call(group.fastSyncRead if self._fast else group.txRxPacket)
        except OSError as exc:
            self._port_lost("sync read", exc)
        except (ValueError, IndexError) as exc:
            log.debug("bus %s: sync read raised %s", self.name, exc)
            result = None
        now = time.monotonic()
        if result != COMM_SUCCESS:
            missing = [i for i in self._ids if len(group.data_dict.get(i) or ()) != len(INDIRECT_LAYOUT)]
            device = self._device(missing[0]) if missing and not self._fast else self.name
            detail = self._ph.getTxRxResult(result) if isinstance(result, int) else "port failure"
            self._communication_failure(device, f"sync read failed ({detail}); no data from "
                                                f"{', '.join(self._label(i) for i in missing) or 'unknown'}")
            return dict(self._last_states)
        self._failures = 0
        raw: dict[int, tuple[int, int, int, int, int]] = {}
        states: dict[str, MotorState] = {}
        cps_unit = self._velocity_unit_counts
        amp_unit = self.model.current_unit_a
        for device_id in self._ids:
            values = _STATE.unpack(bytes(group.data_dict[device_id]))
            raw[device_id] = values
            hw, torque, current, velocity, position = values
            motor = self._by_id[device_id]
            code = hw
            if hw:
                message = describe_hardware_error(hw)
            elif torque == 0 and self._state is LifecycleState.ACTIVE:
                code, message = FAULT_TORQUE_LOST, "torque switched off by the servo (reboot or power loss?)"
            if code and motor.name not in self._faults:
                self.mark_fault(motor.name, code, f"{self._label(device_id)}: {message}")
            states[motor.name] = MotorState(
                position=motor.from_counts(position),
                velocity=motor.velocity_from_counts(velocity * cps_unit),
                effort=current * amp_unit,
                status=hw,
                fault_code=code,
                enabled=torque == 1,
                timestamp=now,
            )
        self._last_raw = raw
        self._last_states = states
        if enabling and self._state is LifecycleState.FAULT:
            # MotorBus.enable sets ACTIVE after this read; a fault seen here must abort the enable instead
            device, (code, message) = next(iter(self._faults.items()))
            raise DeviceFault(device, code, f"fault while enabling: {message}")
        return dict(states)

    def _port_lost(self, what: str, exc: OSError) -> NoReturn:
        """The serial port itself failed (unplugged adapter, emulator's pseudo-terminal gone): FAULT and
        :class:`BusConnectionLost`, so the owner reopens the port once it is back."""
        message = f"{what}: port {self._port_name!r} failed: {exc}"
        self.mark_fault(self.name, FAULT_COMMUNICATION, f"connection lost ({message})")
        raise BusConnectionLost(f"bus {self.name!r}: connection lost: {message}") from exc

    def _communication_failure(self, device: str, message: str) -> None:
        """Count a failed transaction; after ``max_consecutive_failures`` in a row, FAULT and BusTimeout."""
        self._failures += 1
        log.warning("bus %s: %s (%d/%d)", self.name, message, self._failures, self._max_failures)
        if self._failures >= self._max_failures or not self._last_states:
            if self._failures >= self._max_failures:
                self.mark_fault(device, FAULT_COMMUNICATION, f"{message} ({self._failures} consecutive failures)")
            raise BusTimeout(device, message)

    def _reset_fault(self) -> None:
        """Reboot every servo named in a fault, wait until it answers, configure it again (torque off)."""
        faulted = {self.motors[n].device_id for n in self._faults if n in self.motors}
        for device_id in sorted(faulted):
            try:  # not retried: a servo whose answer got lost is already rebooting
                self._txrx("reboot", device_id, self._ph.reboot, retries=0)
            except BusTimeout as exc:
                log.warning("bus %s: %s; waiting for it to come back anyway", self.name, exc)
        deadline = time.monotonic() + float(self._reboot_timeout)
        for device_id in self._ids:
            while self._ping(device_id, 1) is None:
                if time.monotonic() > deadline:
                    raise BusTimeout(self._device(device_id),
                                     f"id {device_id}: silent {self._reboot_timeout} s after reboot")
        for device_id in self._ids:
            self._configure(device_id)
        self._failures = 0
        self._last_states = {}
        states = self._read()
        bad = [(n, s.fault_code) for n, s in states.items() if s.fault_code]
        if bad:
            name, code = bad[0]
            raise DeviceFault(name, code, f"still reports {describe_hardware_error(code)} after reboot")
