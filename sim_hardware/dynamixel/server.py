"""``DynamixelEmulator``: N emulated servos answering protocol 2.0 on a pseudo-terminal.

A background thread reads instruction packets from the pty master, executes them on the
addressed :class:`~sim_hardware.dynamixel.servo.Servo` objects and writes status packets back,
honouring each servo's return delay time and status return level. Clients (dynamixel-sdk,
pyserial) open :attr:`DynamixelEmulator.port`, the slave device, as they would a USB adapter.
Fault injection (dropped, delayed or corrupted packets; overheating, overload, bad input
voltage, disconnected servos) goes through :meth:`inject`/:meth:`clear`, or over ZeroMQ through
:meth:`handle_control` served by :class:`models.emulator_control.ControlServer`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import select
import threading
import time
import tty
from collections.abc import Iterable, Mapping
from typing import Any

from sim_hardware.dynamixel.control_table import get_model
from sim_hardware.dynamixel.protocol import (
    BROADCAST_ID,
    Instruction,
    PacketParser,
    ResultError,
    crc16,
    status_packet,
)
from sim_hardware.dynamixel.servo import AMBIENT_TEMPERATURE_C, NOMINAL_VOLTAGE_V, Servo

log = logging.getLogger(__name__)

#: Faults accepted by :meth:`DynamixelEmulator.inject`.
DEVICE_FAULTS = ("overheat", "overload", "voltage", "electrical_shock", "encoder", "disconnect")
BUS_FAULTS = ("drop", "delay", "corrupt")
#: Buffered bytes older than this when new bytes arrive are a dead partial packet and are dropped.
INTER_PACKET_TIMEOUT_S = 0.05


def parse_ids(text: str) -> list[int]:
    """Parse an id list such as ``"1-13"`` or ``"1,3,5-7"`` (ValueError naming the bad part)."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise ValueError(f"empty entry in id list {text!r}")
        try:
            if "-" in part:
                lo_s, hi_s = part.split("-", 1)
                lo, hi = int(lo_s), int(hi_s)
                if lo > hi:
                    raise ValueError
                ids.extend(range(lo, hi + 1))
            else:
                ids.append(int(part))
        except ValueError:
            raise ValueError(f"bad id range {part!r} in {text!r} (expected N or N-M)") from None
    for i in ids:
        if not 0 <= i <= 252:
            raise ValueError(f"id {i} outside 0-252 in {text!r}")
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate ids in {text!r}")
    return ids


class DynamixelEmulator:
    """Serve emulated servos of one model on a pty from a background thread.

    ``initial_positions`` gives each servo's starting Present Position in counts (one int for
    all, or a map by id; default 0). For a driver's motors, ``{m.device_id: m.to_counts(neutral)}``
    starts every servo at its neutral pose, which ``DynamixelBus.enable`` requires to be in range.
    ``reboot_time_s`` is how long a rebooting servo is silent.
    Use as a context manager or call :meth:`start` / :meth:`close`.
    """

    def __init__(
        self,
        ids: Iterable[int],
        model: str = "XM430-W350",
        *,
        initial_positions: int | Mapping[int, int] = 0,
        reboot_time_s: float = 0.05,
        seed: int | None = None,
    ) -> None:
        self.model = get_model(model)
        id_list = list(ids)
        if not id_list:
            raise ValueError("an emulated bus needs at least one servo id")
        if len(set(id_list)) != len(id_list):
            raise ValueError(f"duplicate servo ids in {id_list}")
        for i in id_list:
            if not isinstance(i, int) or not 0 <= i <= 252:
                raise ValueError(f"servo id {i!r} outside 0-252")
        self.servos: list[Servo] = []
        for i in id_list:
            start = initial_positions if isinstance(initial_positions, int) else initial_positions.get(i, 0)
            self.servos.append(Servo(self.model, i, initial_position=int(start)))
        self._by_id: dict[int, Servo] = {}
        self._reindex()
        self.reboot_time_s = reboot_time_s
        self._lock = threading.RLock()
        self._rng = random.Random(seed)
        self.drop_rate = 0.0
        self.corrupt_rate = 0.0
        self.delay_rate = 0.0
        self.delay_s = 0.0
        self._disconnected: set[int] = set()
        self.packets_in = 0
        self.packets_out = 0
        self.crc_errors = 0
        self._master: int | None = None
        self._slave: int | None = None
        self._port: str | None = None
        self._link: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._parser = PacketParser()

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        """Path of the pty slave device that clients open."""
        if self._port is None:
            raise RuntimeError("emulator not started")
        return self._port

    @property
    def ids(self) -> list[int]:
        """Servo ids in ascending order."""
        with self._lock:
            return sorted(self._by_id)

    def start(self) -> DynamixelEmulator:
        """Create the pty (raw mode) and start serving; returns self."""
        if self._thread is not None:
            return self
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._port = os.ttyname(slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="dynamixel-emulator", daemon=True)
        self._thread.start()
        return self

    def link(self, path: str) -> None:
        """Make ``path`` a symlink to the slave device (replacing an existing link there)."""
        tmp = f"{path}.tmp{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(self.port, tmp)
        os.replace(tmp, path)
        self._link = path

    def close(self) -> None:
        """Stop serving, close the pty and remove the link if this emulator made one."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        if self._link is not None:
            with contextlib.suppress(FileNotFoundError):
                if os.path.islink(self._link):
                    os.unlink(self._link)
            self._link = None

    def __enter__(self) -> DynamixelEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ ground truth and faults
    def servo(self, device_id: int) -> Servo:
        """The servo answering to ``device_id`` (KeyError naming it otherwise)."""
        with self._lock:
            try:
                return self._by_id[device_id]
            except KeyError:
                raise KeyError(f"no emulated servo with id {device_id}") from None

    def positions(self) -> dict[int, float]:
        """Ground-truth shaft positions in counts by id (motion advanced to now)."""
        with self._lock:
            now = time.monotonic()
            out = {}
            for i, s in self._by_id.items():
                s.advance(now)
                out[i] = s.shaft
            return out

    def inject(self, fault: str, device: int | None = None, **params: Any) -> None:
        """Start a fault. Bus faults take ``rate`` (0..1; delay also ``seconds``); device faults a ``device``.

        ``overheat`` raises the temperature above the limit (``celsius``, default limit + 10),
        ``overload`` holds the motor at its current limit, ``voltage`` sets the input voltage
        (``volts``, default 6.0), ``electrical_shock``/``encoder`` latch their error bit,
        ``disconnect`` makes the servo silent.
        """
        with self._lock:
            if fault in BUS_FAULTS:
                rate = float(params.get("rate", 1.0))
                if not 0.0 <= rate <= 1.0:
                    raise ValueError(f"fault {fault!r}: rate {rate!r} outside 0..1")
                if fault == "drop":
                    self.drop_rate = rate
                elif fault == "corrupt":
                    self.corrupt_rate = rate
                else:
                    seconds = float(params.get("seconds", 0.05))
                    if not 0.0 <= seconds <= 10.0:
                        raise ValueError(f"fault 'delay': seconds {seconds!r} outside 0..10")
                    self.delay_rate, self.delay_s = rate, seconds
                return
            if fault not in DEVICE_FAULTS:
                raise ValueError(f"unknown fault {fault!r}; known: {', '.join(BUS_FAULTS + DEVICE_FAULTS)}")
            if device is None:
                raise ValueError(f"fault {fault!r} needs a device id")
            servo = self.servo(int(device))
            servo.advance()
            if fault == "overheat":
                servo.temperature = float(params.get("celsius", servo.memory[31] + 10))
            elif fault == "overload":
                servo.overload_condition = True
            elif fault == "voltage":
                servo.voltage = float(params.get("volts", 6.0))
            elif fault == "electrical_shock":
                servo.latched_errors |= 0x10
            elif fault == "encoder":
                servo.latched_errors |= 0x08
            elif fault == "disconnect":
                self._disconnected.add(int(device))
            servo.advance()

    def clear(self, fault: str | None = None, device: int | None = None) -> None:
        """End fault conditions (all, one kind, or one device's); latched error bits still need a reboot."""
        with self._lock:
            if fault in (None, "drop"):
                self.drop_rate = 0.0
            if fault in (None, "corrupt"):
                self.corrupt_rate = 0.0
            if fault in (None, "delay"):
                self.delay_rate, self.delay_s = 0.0, 0.0
            if fault is not None and fault not in BUS_FAULTS + DEVICE_FAULTS:
                raise ValueError(f"unknown fault {fault!r}")
            targets = [self.servo(int(device))] if device is not None else list(self.servos)
            for servo in targets:
                if fault in (None, "overheat"):
                    servo.temperature = AMBIENT_TEMPERATURE_C
                if fault in (None, "overload"):
                    servo.overload_condition = False
                if fault in (None, "voltage"):
                    servo.voltage = NOMINAL_VOLTAGE_V
                if fault in (None, "disconnect"):
                    self._disconnected.discard(servo.device_id)

    def status(self) -> dict[str, Any]:
        """A snapshot for the control channel: per-servo state and the active bus faults."""
        with self._lock:
            now = time.monotonic()
            servos = []
            for i in sorted(self._by_id):
                s = self._by_id[i]
                s.advance(now)
                servos.append({
                    "id": i, "position": s.reported_position(), "torque": s.torque_enabled,
                    "hardware_error": s.hardware_error, "temperature": round(s.temperature, 2),
                    "voltage": s.voltage, "disconnected": i in self._disconnected,
                })
            return {
                "model": self.model.name, "port": self._port, "servos": servos,
                "drop_rate": self.drop_rate, "corrupt_rate": self.corrupt_rate,
                "delay_rate": self.delay_rate, "delay_s": self.delay_s,
                "packets_in": self.packets_in, "packets_out": self.packets_out,
            }

    def handle_control(self, request: Mapping[str, Any]) -> dict[str, Any]:
        """ControlServer handler: ``inject``, ``clear`` and ``status`` ops."""
        op = request.get("op")
        if op == "inject":
            fault = request.get("fault")
            if not isinstance(fault, str):
                raise ValueError("inject needs a 'fault' name")
            extra = {k: v for k, v in request.items() if k not in ("op", "fault", "device")}
            self.inject(fault, request.get("device"), **extra)
            return {"injected": fault, "device": request.get("device")}
        if op == "clear":
            self.clear(request.get("fault"), request.get("device"))
            return {"cleared": request.get("fault") or "all", "device": request.get("device")}
        if op == "status":
            return self.status()
        if op == "positions":
            return {"positions": {str(k): v for k, v in self.positions().items()}}
        raise ValueError(f"unknown op {op!r}; expected inject, clear, status or positions")

    # ------------------------------------------------------------------ serving
    def _reindex(self) -> None:
        self._by_id = {s.device_id: s for s in self.servos}

    def _serve(self) -> None:
        master = self._master
        assert master is not None
        poll = select.poll()
        poll.register(master, select.POLLIN)
        last_rx = 0.0
        while not self._stop.is_set():
            try:
                if not poll.poll(100):
                    continue
                data = os.read(master, 65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                log.debug("pty read failed: %s", exc)
                time.sleep(0.01)
                continue
            if not data:
                continue
            now = time.monotonic()
            if self._parser.pending() and now - last_rx > INTER_PACKET_TIMEOUT_S:
                self._parser.clear()  # a truncated packet from an earlier client must not swallow this one
            last_rx = now
            for packet in self._parser.feed(data):
                try:
                    with self._lock:
                        replies = self._execute(packet)
                except Exception:  # a bad packet must never kill the bus
                    log.exception("emulator failed on packet %s", packet.raw.hex())
                    continue
                for delay, reply in replies:
                    self._send(delay, reply)

    def _send(self, delay: float, reply: bytes) -> None:
        if delay > 0:
            deadline = time.perf_counter() + delay
            if delay > 2e-4:
                time.sleep(delay - 1e-4)
            while time.perf_counter() < deadline:
                pass
        if self.corrupt_rate and self._rng.random() < self.corrupt_rate:
            reply = reply[:-1] + bytes(((reply[-1] ^ 0x5A),))
        view = memoryview(reply)
        master = self._master
        while view and master is not None:
            try:
                n = os.write(master, view)
            except BlockingIOError:
                select.select([], [master], [], 0.01)
                continue
            except OSError:
                return
            view = view[n:]
        self.packets_out += 1

    def _responder(self, device_id: int) -> Servo | None:
        servo = self._by_id.get(device_id)
        if servo is None or device_id in self._disconnected:
            return None
        if servo.unresponsive_until and time.monotonic() < servo.unresponsive_until:
            return None
        return servo

    def _execute(self, packet) -> list[tuple[float, bytes]]:
        """Run one instruction packet; return (delay before sending, status packet) pairs in order."""
        self.packets_in += 1
        if self.drop_rate and self._rng.random() < self.drop_rate:
            return []
        extra = self.delay_s if self.delay_rate and self._rng.random() < self.delay_rate else 0.0
        inst, params, target = packet.instruction, packet.params, packet.device_id
        if inst == Instruction.STATUS:
            return []  # our own echo or another device's answer
        if not packet.crc_ok:
            self.crc_errors += 1
            servo = self._responder(target) if target != BROADCAST_ID else None
            if servo is None or servo.status_return_level < 2:
                return []
            return [(servo.return_delay_s + extra, status_packet(target, ResultError.CRC | servo.alert))]
        now = time.monotonic()
        replies: list[tuple[float, bytes]] = []

        def answer(servo: Servo, error: int, data: bytes = b"", level: int = 2) -> None:
            # id, status return level and return delay as they were when the instruction arrived
            sid, srl, delay = before.get(id(servo)) or (servo.device_id, servo.status_return_level,
                                                         servo.return_delay_s)
            if srl >= level:
                replies.append((delay + (extra if not replies else 0.0), status_packet(sid, error, data)))

        before: dict[int, tuple[int, int, float]] = {}

        if inst == Instruction.PING:
            servos = self._targets(target)
            for servo in servos:
                answer(servo, servo.alert, servo.ping_params(), level=0)
            return replies
        if inst in (Instruction.SYNC_WRITE, Instruction.BULK_WRITE):
            if target == BROADCAST_ID:
                self._multi_write(inst, params, now)
            return []
        if inst in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ, Instruction.BULK_READ):
            if target != BROADCAST_ID:
                return []
            return self._multi_read(inst, params, now, extra)
        if inst == Instruction.ACTION:
            for servo in self._targets(target):
                error = servo.action()
                if target != BROADCAST_ID:
                    answer(servo, error)
            self._reindex()
            return replies
        servo = self._responder(target)
        if servo is None:
            if target == BROADCAST_ID:
                for s in self._targets(target):
                    self._unicast(s, inst, params, lambda *a, **k: None)
                self._reindex()
            return []
        servo.advance(now)
        before[id(servo)] = (servo.device_id, servo.status_return_level, servo.return_delay_s)
        self._unicast(servo, inst, params, answer)
        self._reindex()
        return replies

    def _targets(self, target: int) -> list[Servo]:
        if target == BROADCAST_ID:
            return [s for i, s in sorted(self._by_id.items()) if self._responder(i) is not None]
        servo = self._responder(target)
        return [servo] if servo is not None else []

    def _unicast(self, servo: Servo, inst: int, params: bytes, answer) -> None:
        if inst == Instruction.READ:
            if len(params) != 4:
                answer(servo, ResultError.DATA_LENGTH | servo.alert, level=1)
                return
            address = params[0] | (params[1] << 8)
            length = params[2] | (params[3] << 8)
            error, data = servo.read(address, length)
            answer(servo, error, data, level=1)
        elif inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(params) < 3:
                answer(servo, ResultError.DATA_LENGTH | servo.alert)
                return
            address = params[0] | (params[1] << 8)
            if inst == Instruction.WRITE:
                answer(servo, servo.write(address, params[2:]))
            else:
                answer(servo, servo.reg_write(address, params[2:]))
        elif inst == Instruction.REBOOT:
            answer(servo, servo.alert)
            servo.reboot(self.reboot_time_s)
        elif inst == Instruction.FACTORY_RESET:
            option = params[0] if params else 0xFF
            answer(servo, servo.factory_reset(option))
        elif inst == Instruction.CLEAR:
            answer(servo, ResultError.RESULT_FAIL | servo.alert)  # multi-turn clear: not modelled
        else:
            answer(servo, ResultError.INSTRUCTION | servo.alert)

    def _multi_write(self, inst: int, params: bytes, now: float) -> None:
        if inst == Instruction.SYNC_WRITE:
            if len(params) < 4:
                return
            address = params[0] | (params[1] << 8)
            size = params[2] | (params[3] << 8)
            stride = size + 1
            body = params[4:]
            for k in range(0, len(body) - stride + 1, stride):
                servo = self._responder(body[k])
                if servo is not None:
                    servo.write(address, body[k + 1:k + stride], now=now)
        else:
            k = 0
            while k + 5 <= len(params):
                device_id = params[k]
                address = params[k + 1] | (params[k + 2] << 8)
                size = params[k + 3] | (params[k + 4] << 8)
                data = params[k + 5:k + 5 + size]
                k += 5 + size
                servo = self._responder(device_id)
                if servo is not None and len(data) == size:
                    servo.write(address, data, now=now)
        self._reindex()

    def _multi_read(self, inst: int, params: bytes, now: float, extra: float) -> list[tuple[float, bytes]]:
        requests: list[tuple[int, int, int]] = []
        if inst == Instruction.BULK_READ:
            for k in range(0, len(params) - 4, 5):
                requests.append((params[k], params[k + 1] | (params[k + 2] << 8), params[k + 3] | (params[k + 4] << 8)))
        else:
            if len(params) < 5:
                return []
            address = params[0] | (params[1] << 8)
            size = params[2] | (params[3] << 8)
            requests = [(i, address, size) for i in params[4:]]
        answers: list[tuple[Servo, int, bytes]] = []
        for device_id, address, size in requests:
            servo = self._responder(device_id)
            if servo is None or servo.status_return_level < 1:
                continue
            error, data = servo.read(address, size, now)
            answers.append((servo, error, data))
        if not answers:
            return []
        if inst != Instruction.FAST_SYNC_READ:
            out = []
            for n, (servo, error, data) in enumerate(answers):
                delay = servo.return_delay_s + (extra if n == 0 else 0.0)
                out.append((delay, status_packet(servo.device_id, error, data)))
            return out
        # Fast sync read: one packet from the broadcast id; each device appends error, id, data and
        # a CRC over everything before it; the last device's CRC is the packet CRC.
        total = sum(4 + len(d) for _, _, d in answers)
        length = 1 + total
        buf = bytearray(b"\xff\xff\xfd\x00" + bytes((BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS)))
        crc = crc16(buf)
        for servo, error, data in answers:
            chunk = bytes((error & 0xFF, servo.device_id)) + data
            buf += chunk
            crc = crc16(chunk, crc)
            crc_bytes = bytes((crc & 0xFF, crc >> 8))
            buf += crc_bytes
            crc = crc16(crc_bytes, crc)
        delay = sum(s.return_delay_s for s, _, _ in answers) + extra
        return [(delay, bytes(buf))]


__all__ = ["BUS_FAULTS", "DEVICE_FAULTS", "DynamixelEmulator", "parse_ids"]
