"""Protocol 2.0 framing: CRC against the e-manual's packets, byte stuffing, incremental parsing."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from sim_hardware.dynamixel.protocol import (
    CRC_TABLE,
    Instruction,
    PacketParser,
    crc16,
    instruction_packet,
    status_packet,
    stuff,
    unstuff,
)

# e-manual protocol 2.0 examples
PING_ID1 = bytes.fromhex("FFFFFD0001030001194E")
PING_STATUS_ID1 = bytes.fromhex("FFFFFD0001070055000604 26655D".replace(" ", ""))  # model 1030, fw 0x26


def test_crc_matches_manual_ping_packet() -> None:
    assert crc16(PING_ID1[:-2]) == 0x4E19
    assert instruction_packet(1, Instruction.PING) == PING_ID1


def test_crc_matches_manual_status_packet() -> None:
    assert status_packet(1, 0, bytes((0x06, 0x04, 0x26))) == PING_STATUS_ID1


def test_crc_table_is_polynomial_8005() -> None:
    assert CRC_TABLE[1] == 0x8005
    assert CRC_TABLE[255] == 0x0202
    # continuing a CRC over a split buffer equals one pass
    data = bytes(range(40))
    assert crc16(data[20:], crc16(data[:20])) == crc16(data)


def test_crc_agrees_with_official_sdk() -> None:
    from dynamixel_sdk import PacketHandler

    ph = PacketHandler(2.0)
    data = list(range(256)) * 2
    assert ph.updateCRC(0, data, len(data)) == crc16(bytes(data))


def test_stuffing_example() -> None:
    assert stuff(b"\x03\xff\xff\xfd\x01") == b"\x03\xff\xff\xfd\xfd\x01"
    assert unstuff(b"\x03\xff\xff\xfd\xfd\x01") == b"\x03\xff\xff\xfd\x01"
    packet = instruction_packet(1, Instruction.WRITE, b"\x74\x00\xff\xff\xfd\x00")
    assert packet.count(b"\xff\xff\xfd") == 2  # the header and the stuffed one
    assert b"\xff\xff\xfd\xfd" in packet


@given(st.binary(max_size=200))
def test_stuffing_round_trip(body: bytes) -> None:
    stuffed = stuff(body)
    assert unstuff(stuffed) == body
    # after stuffing, every FF FF FD is followed by FD: no header can appear in the payload
    i = stuffed.find(b"\xff\xff\xfd")
    while i >= 0:
        assert stuffed[i + 3:i + 4] == b"\xfd"
        i = stuffed.find(b"\xff\xff\xfd", i + 4)


@given(st.binary(max_size=120), st.integers(0, 252), st.sampled_from([1, 2, 3, 0x83]))
def test_parser_round_trip_through_sdk_stuffing(params: bytes, device_id: int, inst: int) -> None:
    """Packets framed by the official SDK parse back to the original params."""
    from dynamixel_sdk import PacketHandler

    ph = PacketHandler(2.0)
    tx = [0] * (len(params) + 10)
    tx[4] = device_id
    tx[5] = (len(params) + 3) & 0xFF
    tx[6] = (len(params) + 3) >> 8
    tx[7] = inst
    tx[8:8 + len(params)] = list(params)
    tx = ph.addStuffing(tx)
    total = (tx[5] | tx[6] << 8) + 7
    tx[0:4] = [0xFF, 0xFF, 0xFD, 0x00]
    crc = ph.updateCRC(0, tx, total - 2)
    tx[total - 2] = crc & 0xFF
    tx[total - 1] = crc >> 8
    wire = bytes(tx[:total])
    assert wire == instruction_packet(device_id, inst, params)
    parser = PacketParser()
    # feed byte by byte behind some garbage
    packets = []
    for byte in b"\x00\xff\x12" + wire:
        packets += parser.feed(bytes((byte,)))
    assert len(packets) == 1
    assert packets[0].crc_ok and packets[0].device_id == device_id
    assert packets[0].instruction == inst and packets[0].params == params


def test_parser_flags_bad_crc_and_resyncs() -> None:
    good = instruction_packet(2, Instruction.READ, b"\x84\x00\x04\x00")
    bad = bytearray(good)
    bad[-1] ^= 0xFF
    parser = PacketParser()
    packets = parser.feed(bytes(bad) + good)
    assert [p.crc_ok for p in packets] == [False, True]
    assert packets[1].params == b"\x84\x00\x04\x00"
    # an absurd length field is skipped, not waited for
    junk = b"\xff\xff\xfd\x00\x01\xff\xff"
    assert [p.device_id for p in parser.feed(junk + good)] == [2]
    assert parser.pending() == 0
