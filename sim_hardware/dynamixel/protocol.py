"""Dynamixel protocol 2.0 framing: CRC-16, byte stuffing, instruction parsing and status packets.

A packet is ``FF FF FD 00 | id | length (LE16) | instruction | params | CRC16 (LE)``; ``length``
counts instruction, params and CRC. Inside the params every ``FF FF FD`` is sent as
``FF FF FD FD`` (stuffing) so a header can never appear in the payload; the CRC covers the
packet as transmitted, stuffing included. Only the standard library is used so that both the
emulator and tests can frame packets cheaply.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
#: Longest packet accepted from the wire (the official SDK caps packets at 1 KiB too).
MAX_PACKET_LENGTH = 1024


class Instruction(enum.IntEnum):
    """Instruction codes of protocol 2.0."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


class ResultError(enum.IntEnum):
    """The low 7 bits of a status packet's error byte (the e-manual's "result" errors)."""

    NONE = 0x00
    RESULT_FAIL = 0x01
    INSTRUCTION = 0x02
    CRC = 0x03
    DATA_RANGE = 0x04
    DATA_LENGTH = 0x05
    DATA_LIMIT = 0x06
    ACCESS = 0x07


#: Set in a status packet's error byte while the device has a hardware error latched.
ALERT_BIT = 0x80


class HardwareError(enum.IntFlag):
    """Bits of the Hardware Error Status item (address 70 on X-series servos)."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


def _make_crc_table() -> tuple[int, ...]:
    """CRC-16 with polynomial 0x8005, MSB first, no reflection (CRC-16/BUYPASS)."""
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


CRC_TABLE: tuple[int, ...] = _make_crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC of ``data`` as the protocol computes it, continuing from ``crc``."""
    table = CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ byte) & 0xFF]
    return crc


def stuff(params: bytes | bytearray) -> bytes:
    """Insert an extra ``FD`` after every ``FF FF FD`` so the payload cannot contain a header.

    ``params`` is the part after the length field (instruction or error onwards, without CRC);
    the scan runs over instruction + params as the SDK does.
    """
    if b"\xff\xff\xfd" not in params:
        return bytes(params)
    out = bytearray()
    n = len(params)
    i = 0
    while i < n:
        if params[i] == 0xFD and i >= 2 and params[i - 1] == 0xFF and params[i - 2] == 0xFF:
            out.append(0xFD)
            out.append(0xFD)
        else:
            out.append(params[i])
        i += 1
    return bytes(out)


def unstuff(params: bytes | bytearray) -> bytes:
    """Inverse of :func:`stuff`: drop the ``FD`` that follows each ``FF FF FD``."""
    if b"\xff\xff\xfd\xfd" not in params:
        return bytes(params)
    out = bytearray()
    n = len(params)
    i = 0
    while i < n:
        out.append(params[i])
        if params[i] == 0xFD and i >= 2 and params[i - 1] == 0xFF and params[i - 2] == 0xFF and i + 1 < n \
                and params[i + 1] == 0xFD:
            i += 1  # skip the stuffed byte
        i += 1
    return bytes(out)


def build_packet(device_id: int, body: bytes | bytearray, *, stuffed: bool = True) -> bytes:
    """Frame ``body`` (instruction or 0x55+error, then params) for ``device_id``: header, length, CRC."""
    payload = stuff(body) if stuffed else bytes(body)
    length = len(payload) + 2
    head = HEADER + bytes((device_id & 0xFF, length & 0xFF, length >> 8))
    crc = crc16(payload, crc16(head))
    return head + payload + bytes((crc & 0xFF, crc >> 8))


def instruction_packet(device_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """An instruction packet as a master sends it."""
    return build_packet(device_id, bytes((instruction,)) + bytes(params))


def status_packet(device_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A status packet (instruction 0x55) with ``error`` (result code | alert bit) and params."""
    return build_packet(device_id, bytes((Instruction.STATUS, error & 0xFF)) + bytes(params))


@dataclass(frozen=True, slots=True)
class Packet:
    """One received packet, unstuffed: ``instruction`` is 0x55 for status packets."""

    device_id: int
    instruction: int
    params: bytes
    crc_ok: bool
    raw: bytes

    @property
    def error(self) -> int:
        """Error byte of a status packet."""
        return self.params[0] if self.instruction == Instruction.STATUS and self.params else 0


class PacketParser:
    """Incremental parser: feed bytes as they arrive, get complete packets back.

    Garbage before a header is skipped; a length beyond :data:`MAX_PACKET_LENGTH` drops the
    header and resynchronises. Packets whose CRC fails are still returned (``crc_ok`` False)
    so a device can answer with a CRC error as the e-manual describes.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def pending(self) -> int:
        """Bytes buffered but not yet part of a complete packet."""
        return len(self._buf)

    def clear(self) -> None:
        self._buf.clear()

    def feed(self, data: bytes | bytearray) -> list[Packet]:
        """Append received bytes; return every packet completed by them."""
        buf = self._buf
        buf += data
        packets: list[Packet] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # keep a possible partial header at the end
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and buf[-k:] == HEADER[:k]:
                        keep = k
                        break
                del buf[: len(buf) - keep]
                return packets
            if start:
                del buf[:start]
            if len(buf) < 7:
                return packets
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > MAX_PACKET_LENGTH:
                del buf[:1]
                continue
            total = 7 + length
            if len(buf) < total:
                return packets
            raw = bytes(buf[:total])
            del buf[:total]
            crc = raw[-2] | (raw[-1] << 8)
            crc_ok = crc16(raw[:-2]) == crc
            body = unstuff(raw[7:-2])
            packets.append(Packet(raw[4], body[0], body[1:], crc_ok, raw))


def u16(value: int) -> bytes:
    """Little-endian 16-bit field."""
    return (value & 0xFFFF).to_bytes(2, "little")


def u32(value: int) -> bytes:
    """Little-endian 32-bit field (negative values in two's complement)."""
    return (value & 0xFFFFFFFF).to_bytes(4, "little")
