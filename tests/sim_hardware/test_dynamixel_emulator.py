"""The emulator on a pty against the official client (dynamixel-sdk PortHandler/PacketHandler/groups)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import pytest
from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupBulkWrite,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from sim_hardware.dynamixel import DynamixelEmulator, parse_ids
from sim_hardware.dynamixel.protocol import ALERT_BIT, Instruction, ResultError, instruction_packet
from tests._wait import wait_until

IDS = [1, 2, 3, 4, 5]


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    """Widen the SDK's answer window (2 × latency timer + 2 ms, about 0.5 s) so a loaded test machine does not
    flake."""
    import dynamixel_sdk.port_handler

    monkeypatch.setattr(dynamixel_sdk.port_handler, "LATENCY_TIMER", 250)


@pytest.fixture
def emu() -> Iterator[DynamixelEmulator]:
    with DynamixelEmulator(IDS, initial_positions={i: 1000 + 100 * i for i in IDS}, reboot_time_s=0.05) as e:
        yield e


@pytest.fixture
def port(emu: DynamixelEmulator) -> Iterator[PortHandler]:
    handler = PortHandler(emu.port)
    assert handler.openPort()
    assert handler.setBaudRate(4_000_000)
    yield handler
    handler.closePort()


@pytest.fixture
def ph() -> PacketHandler:
    return PacketHandler(2.0)


def fast_bus(port: PortHandler, ph: PacketHandler) -> None:
    for i in IDS:
        assert ph.write1ByteTxRx(port, i, 9, 0) == (COMM_SUCCESS, 0)


def s32(v: int) -> int:
    return v - (1 << 32) if v >= 1 << 31 else v


def test_ping_each_and_missing(port: PortHandler, ph: PacketHandler) -> None:
    for i in IDS:
        assert ph.ping(port, i) == (1020, COMM_SUCCESS, 0)
    _, result, _ = ph.ping(port, 42)
    assert result == COMM_RX_TIMEOUT


def test_broadcast_ping_answers_every_id(port: PortHandler, ph: PacketHandler) -> None:
    found, result = ph.broadcastPing(port)
    assert result == COMM_SUCCESS
    assert found == {i: [1020, 52] for i in IDS}


def test_read_write_1_2_4_bytes(port: PortHandler, ph: PacketHandler) -> None:
    assert ph.write1ByteTxRx(port, 2, 65, 1) == (COMM_SUCCESS, 0)  # LED
    assert ph.read1ByteTxRx(port, 2, 65) == (1, COMM_SUCCESS, 0)
    assert ph.write2ByteTxRx(port, 2, 84, 1234) == (COMM_SUCCESS, 0)  # position P gain
    assert ph.read2ByteTxRx(port, 2, 84) == (1234, COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 2, 112, 77) == (COMM_SUCCESS, 0)  # profile velocity
    assert ph.read4ByteTxRx(port, 2, 112) == (77, COMM_SUCCESS, 0)
    assert ph.read2ByteTxRx(port, 2, 0) == (1020, COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 2, 132) == (1200, COMM_SUCCESS, 0)
    # result errors travel in the status packet
    assert ph.write2ByteTxRx(port, 2, 0, 5) == (COMM_SUCCESS, ResultError.ACCESS)
    assert ph.write1ByteTxRx(port, 2, 64, 1) == (COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 2, 11, 4) == (COMM_SUCCESS, ResultError.ACCESS)  # EEPROM locked
    assert ph.write4ByteTxRx(port, 2, 116, 5000) == (COMM_SUCCESS, ResultError.DATA_LIMIT)


def test_sync_write_and_sync_read_reach_goals(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    fast_bus(port, ph)
    torque = GroupSyncWrite(port, ph, 64, 1)
    goals = GroupSyncWrite(port, ph, 116, 4)
    for i in IDS:
        torque.addParam(i, [1])
        goals.addParam(i, list((2000 + i).to_bytes(4, "little")))
    assert goals.txPacket() == COMM_SUCCESS
    assert torque.txPacket() == COMM_SUCCESS
    reader = GroupSyncRead(port, ph, 132, 4)
    for i in IDS:
        assert reader.addParam(i)
    deadline = time.monotonic() + 5.0
    while True:
        assert reader.txRxPacket() == COMM_SUCCESS
        positions = {i: reader.getData(i, 132, 4) for i in IDS}
        if positions == {i: 2000 + i for i in IDS} or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert positions == {i: 2000 + i for i in IDS}
    assert {i: round(p) for i, p in emu.positions().items()} == positions  # ground truth agrees


def test_fast_sync_read(port: PortHandler, ph: PacketHandler) -> None:
    reader = GroupSyncRead(port, ph, 126, 10)  # current, velocity, position
    for i in IDS:
        reader.addParam(i)
    assert reader.fastSyncRead() == COMM_SUCCESS
    assert {i: reader.getData(i, 132, 4) for i in IDS} == {i: 1000 + 100 * i for i in IDS}
    assert all(reader.getData(i, 128, 4) == 0 for i in IDS)


def test_bulk_read_and_bulk_write(port: PortHandler, ph: PacketHandler) -> None:
    writer = GroupBulkWrite(port, ph)
    assert writer.addParam(1, 65, 1, [1])
    assert writer.addParam(3, 112, 4, list((321).to_bytes(4, "little")))
    assert writer.txPacket() == COMM_SUCCESS
    reader = GroupBulkRead(port, ph)
    assert reader.addParam(1, 65, 1)
    assert reader.addParam(3, 112, 4)
    assert reader.addParam(5, 132, 4)
    assert reader.txRxPacket() == COMM_SUCCESS
    assert reader.getData(1, 65, 1) == 1
    assert reader.getData(3, 112, 4) == 321
    assert reader.getData(5, 132, 4) == 1500


def test_reg_write_then_action(port: PortHandler, ph: PacketHandler) -> None:
    assert ph.regWriteTxRx(port, 4, 65, 1, [1]) == (COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 4, 69) == (1, COMM_SUCCESS, 0)  # registered instruction
    assert ph.read1ByteTxRx(port, 4, 65) == (0, COMM_SUCCESS, 0)  # not applied yet
    assert ph.action(port, BROADCAST_ID) == COMM_SUCCESS  # broadcast: no answer to wait on
    wait_until(lambda: ph.read1ByteTxRx(port, 4, 65) == (1, COMM_SUCCESS, 0), 10, "the registered write applied")
    assert ph.read1ByteTxRx(port, 4, 69) == (0, COMM_SUCCESS, 0)


def test_torque_off_means_no_motion(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    assert ph.write4ByteTxRx(port, 1, 116, 3000) == (COMM_SUCCESS, 0)
    time.sleep(0.2)
    assert ph.read4ByteTxRx(port, 1, 132) == (1100, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, 122) == (0, COMM_SUCCESS, 0)  # not moving
    assert round(emu.positions()[1]) == 1100


def test_hardware_error_alert_and_reboot(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    assert ph.write1ByteTxRx(port, 3, 64, 1) == (COMM_SUCCESS, 0)
    emu.inject("overheat", 3)
    model, result, error = ph.ping(port, 3)
    assert model == 1020
    assert result == COMM_SUCCESS and error == ALERT_BIT
    assert ph.read1ByteTxRx(port, 3, 70) == (0x04, COMM_SUCCESS, ALERT_BIT)
    assert ph.read1ByteTxRx(port, 3, 64) == (0, COMM_SUCCESS, ALERT_BIT)  # shutdown turned torque off
    assert ph.read1ByteTxRx(port, 3, 146)[0] >= 90
    emu.clear("overheat", 3)
    emu.reboot_time_s = 2.0  # silent long enough to be seen silent on a loaded host
    assert ph.reboot(port, 3) == (COMM_SUCCESS, ALERT_BIT)  # answered before rebooting
    assert ph.ping(port, 3)[1] == COMM_RX_TIMEOUT  # silent while booting
    wait_until(lambda: ph.read1ByteTxRx(port, 3, 70) == (0, COMM_SUCCESS, 0), 10, "servo 3 back, its error cleared")
    for fault, bit in (("overload", 0x20), ("voltage", 0x01), ("electrical_shock", 0x10), ("encoder", 0x08)):
        emu.inject(fault, 2)
        assert ph.read1ByteTxRx(port, 2, 70)[0] & bit, fault


def test_factory_reset(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    assert ph.write1ByteTxRx(port, 5, 9, 0) == (COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 5, 44, 100) == (COMM_SUCCESS, 0)
    assert ph.factoryReset(port, 5, 0x01) == (COMM_SUCCESS, 0)  # all but the id
    assert ph.read4ByteTxRx(port, 5, 44) == (200, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 5, 9) == (250, COMM_SUCCESS, 0)
    assert ph.factoryReset(port, 5, 0xFF) == (COMM_SUCCESS, 0)  # everything: the id becomes 1
    assert ph.ping(port, 5)[1] == COMM_RX_TIMEOUT
    assert emu.ids.count(1) == 1 and 5 not in emu.ids


def test_id_change_takes_effect(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    assert ph.write1ByteTxRx(port, 4, 7, 40) == (COMM_SUCCESS, 0)
    assert ph.ping(port, 40) == (1020, COMM_SUCCESS, 0)
    assert 4 not in emu.ids


def test_status_return_level_and_return_delay(port: PortHandler, ph: PacketHandler) -> None:
    assert ph.write1ByteTxRx(port, 1, 9, 254) == (COMM_SUCCESS, 0)  # 508 µs
    t = time.perf_counter()
    assert ph.ping(port, 1)[1] == COMM_SUCCESS
    assert time.perf_counter() - t >= 508e-6
    assert ph.write1ByteTxRx(port, 1, 68, 1) == (COMM_SUCCESS, 0)  # answer ping and read only
    assert ph.read1ByteTxRx(port, 1, 68) == (1, COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, 65, 1)[0] == COMM_RX_TIMEOUT  # no status for a write
    assert ph.read1ByteTxRx(port, 1, 65) == (1, COMM_SUCCESS, 0)  # but it was applied
    ph.write1ByteTxOnly(port, 1, 68, 0)
    assert ph.read1ByteTxRx(port, 1, 65)[1] == COMM_RX_TIMEOUT
    assert ph.ping(port, 1)[1] == COMM_SUCCESS  # ping always answers


def test_bad_crc_gets_crc_error_status(emu: DynamixelEmulator) -> None:
    import serial

    with serial.Serial(emu.port, 1_000_000, timeout=10) as ser:
        packet = bytearray(instruction_packet(2, Instruction.READ, b"\x84\x00\x04\x00"))
        packet[-1] ^= 0x55
        ser.write(bytes(packet))
        reply = ser.read(11)
        assert reply[:5] == b"\xff\xff\xfd\x00\x02" and reply[8] == ResultError.CRC
        # a broadcast with a bad CRC gets no answer at all
        bad = bytearray(instruction_packet(0xFE, Instruction.PING))
        bad[-2] ^= 1
        ser.write(bytes(bad))
        ser.timeout = 0.1
        assert ser.read(14) == b""


def test_packet_fault_injection(port: PortHandler, ph: PacketHandler, emu: DynamixelEmulator) -> None:
    emu.inject("drop", rate=1.0)
    assert ph.ping(port, 1)[1] == COMM_RX_TIMEOUT
    emu.clear("drop")
    emu.inject("corrupt", rate=1.0)
    assert ph.ping(port, 1)[1] == COMM_RX_CORRUPT
    emu.clear()
    emu.inject("delay", rate=1.0, seconds=1.5)  # beyond the SDK's answer window (about 0.5 s here)
    assert ph.ping(port, 1)[1] == COMM_RX_TIMEOUT
    emu.clear()
    # the emulator answers again once the late answer is out (the next request clears it from the port)
    wait_until(lambda: ph.ping(port, 1)[1] == COMM_SUCCESS, 10, "servo 1 answering promptly again")
    emu.inject("disconnect", 2)
    assert ph.ping(port, 2)[1] == COMM_RX_TIMEOUT
    assert ph.ping(port, 1)[1] == COMM_SUCCESS
    emu.clear("disconnect")
    assert ph.ping(port, 2)[1] == COMM_SUCCESS
    with pytest.raises(ValueError, match="unknown fault 'melt'"):
        emu.inject("melt", 1)
    with pytest.raises(ValueError, match="rate"):
        emu.inject("drop", rate=2.0)


def test_control_channel_handler(emu: DynamixelEmulator) -> None:
    from models.emulator_control import ControlServer, request

    server = ControlServer("tcp://127.0.0.1:0", emu.handle_control)
    try:
        reply = request(server.endpoint, {"op": "inject", "fault": "overheat", "device": 2})
        assert reply["ok"], reply
        status = request(server.endpoint, {"op": "status"})
        assert status["ok"] and [s["hardware_error"] for s in status["servos"]] == [0, 0x04, 0, 0, 0]
        assert request(server.endpoint, {"op": "clear", "device": 2})["ok"]
        bad = request(server.endpoint, {"op": "inject", "fault": "nope", "device": 1})
        assert not bad["ok"] and "unknown fault" in bad["error"]
    finally:
        server.close()


def test_link_and_close(tmp_path) -> None:
    link = tmp_path / "dxl"
    emu = DynamixelEmulator([1]).start()
    emu.link(str(link))
    assert os.path.realpath(link) == emu.port
    emu.close()
    assert not link.exists() and not link.is_symlink()


def test_parse_ids_and_bad_construction() -> None:
    assert parse_ids("1-3,7") == [1, 2, 3, 7]
    for bad in ("", "3-1", "1,1", "x", "300"):
        with pytest.raises(ValueError):
            parse_ids(bad)
    with pytest.raises(ValueError, match="unknown Dynamixel model"):
        DynamixelEmulator([1], model="AX-12")
    with pytest.raises(ValueError, match="duplicate"):
        DynamixelEmulator([1, 1])


def test_truncated_packet_does_not_swallow_the_next(emu: DynamixelEmulator) -> None:
    import serial

    with serial.Serial(emu.port, 1_000_000, timeout=10) as ser:
        ser.write(instruction_packet(1, Instruction.WRITE, b"\x41\x00\x01")[:9])  # a client died mid-packet
        wait_until(emu._parser.pending, 10, "the emulator holding the partial packet")
        time.sleep(0.1)  # then silence past the emulator's inter-packet timeout (0.05 s): the subject of the test
        ser.reset_input_buffer()
        ser.write(instruction_packet(1, Instruction.PING))
        reply = ser.read(14)
        assert reply[:5] == b"\xff\xff\xfd\x00\x01" and reply[7] == Instruction.STATUS and reply[8] == 0


def test_fast_sync_read_packet_layout(emu: DynamixelEmulator) -> None:
    """One packet from the broadcast id: error, id, data, CRC per servo; each CRC covers all bytes before it."""
    import serial

    from sim_hardware.dynamixel.protocol import crc16

    for i in IDS:
        emu.servo(i).write_item("return_delay_time", 0)
    with serial.Serial(emu.port, 1_000_000, timeout=10) as ser:
        ser.write(instruction_packet(0xFE, Instruction.FAST_SYNC_READ, b"\x84\x00\x04\x00" + bytes((1, 3, 42, 5))))
        reply = ser.read(8 + 3 * 8)
    assert reply[:8] == b"\xff\xff\xfd\x00\xfe" + (1 + 3 * 8).to_bytes(2, "little") + b"\x55"
    for k, device_id in enumerate((1, 3, 5)):  # the missing id 42 is left out, order kept
        chunk = reply[8 + 8 * k: 16 + 8 * k]
        assert chunk[0] == 0 and chunk[1] == device_id
        assert int.from_bytes(chunk[2:6], "little") == 1000 + 100 * device_id
        assert int.from_bytes(chunk[6:8], "little") == crc16(reply[:14 + 8 * k])


def test_sync_read_answers_in_request_order(emu: DynamixelEmulator) -> None:
    import serial

    from sim_hardware.dynamixel.protocol import PacketParser

    with serial.Serial(emu.port, 1_000_000, timeout=10) as ser:
        ser.write(instruction_packet(0xFE, Instruction.SYNC_READ, b"\x84\x00\x04\x00" + bytes((4, 2, 5))))
        data = ser.read(3 * 15)
    packets = PacketParser().feed(data)
    assert [p.device_id for p in packets] == [4, 2, 5]
    assert all(p.crc_ok and p.instruction == Instruction.STATUS for p in packets)
    assert [int.from_bytes(p.params[1:], "little") for p in packets] == [1400, 1200, 1500]


def test_unicast_action_answers_and_without_reg_write_is_an_instruction_error(emu: DynamixelEmulator) -> None:
    import serial

    from sim_hardware.dynamixel.protocol import PacketParser

    with serial.Serial(emu.port, 1_000_000, timeout=10) as ser:
        ser.write(instruction_packet(2, Instruction.ACTION))
        (status,) = PacketParser().feed(ser.read(11))
        assert status.device_id == 2 and status.error == ResultError.INSTRUCTION


def test_rw_items_round_trip(emu: DynamixelEmulator) -> None:
    """Every writable RAM item takes its bounds and reads them back; read-only items refuse writes."""
    servo = emu.servo(1)
    for item in emu.model.items:
        if item.eeprom or item.name.startswith("indirect") or item.name in ("torque_enable", "goal_position",
                                                                            "goal_velocity", "goal_current",
                                                                            "goal_pwm", "status_return_level"):
            continue
        raw = lambda v, it=item: v.to_bytes(it.size, "little", signed=it.signed)  # noqa: E731
        if not item.writable:
            assert servo.write(item.address, raw(item.default)) & 0x7F == ResultError.ACCESS, item.name
            continue
        for value in (item.low, item.high):
            assert servo.write(item.address, raw(value)) == 0, item.name
            assert servo.read(item.address, item.size)[1] == raw(value), item.name
        if item.high < (1 << (8 * item.size - (1 if item.signed else 0))) - 1:
            assert servo.write(item.address, raw(item.high + 1)) & 0x7F == ResultError.DATA_RANGE, item.name
