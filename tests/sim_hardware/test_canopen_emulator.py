"""The emulated CiA 402 drive, driven in-process by canopen's own master (``BaseNode402``) and raw SDO."""

from __future__ import annotations

import struct
import time
import uuid

import can
import canopen
import pytest

from sim_hardware.canopen import drive as drv
from sim_hardware.canopen.network import DriveSet
from sim_hardware.canopen.od import DEVICE_TYPE, build_od, write_eds
from tests._wait import wait_until
from tests.sim_hardware.canopen_master import setup_master as _setup_master


def _channel() -> str:
    return f"test-canopen-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def rig():
    """Two drives on a fresh virtual channel and a canopen master network on the same channel."""
    channel = _channel()
    drives = DriveSet([1, 2], channel=channel, heartbeat_ms=20, seed=1).start()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.1
    net.connect(interface="virtual", channel=channel)
    yield drives, net
    net.sync.stop()
    net.disconnect()
    drives.stop()


def test_object_dictionary_and_eds_round_trip(tmp_path):
    od = build_od(5)
    assert od[0x1000].default == DEVICE_TYPE
    for base in (0x1400, 0x1600, 0x1800, 0x1A00):
        for k in range(4):
            assert base + k in od
    for index in (0x6040, 0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x6065, 0x606C, 0x6077, 0x6078, 0x607A,
                  0x6081, 0x6083, 0x6084, 0x60C2, 0x6502, 0x603F, 0x1017, 0x1018):
        assert index in od, hex(index)
    assert od[0x1800][1].default == 0x185
    path = write_eds(tmp_path / "drive.eds", node_id=5)
    back = canopen.import_od(str(path), 5)
    assert back[0x1000].default == DEVICE_TYPE
    assert back[0x607D][1].default == -(2**31)  # negative defaults survive the EDS round trip
    assert back[0x1A02][2].default == 0x60640020
    assert not list(tmp_path.glob("*.tmp"))


def test_boot_up_heartbeat_and_sdo(rig):
    _, net = rig
    seen: list[int] = []
    net.subscribe(0x701, lambda _id, data, _ts: seen.append(data[0]))
    node = net.add_node(1, canopen.ObjectDictionary())
    assert struct.unpack("<I", node.sdo.upload(0x1000, 0))[0] == DEVICE_TYPE
    assert wait_until(lambda: len(seen) >= 3, 10)
    assert set(seen) == {127}  # pre-operational heartbeats at 0x1017 = 20 ms
    # NMT reset node: boot-up (state 0) then pre-operational again, defaults restored.
    node.sdo.download(0x6065, 0, struct.pack("<I", 123))
    seen.clear()
    net.send_message(0, bytes([0x81, 1]))
    assert wait_until(lambda: 0 in seen and seen[-1] == 127, 10)
    assert struct.unpack("<I", node.sdo.upload(0x6065, 0))[0] == 5000
    # A refused write aborts like a real drive: unsupported mode of operation.
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo.download(0x6060, 0, struct.pack("<b", 3))
    # Mapping an object that is not mappable is refused.
    with pytest.raises(canopen.SdoAbortedError):
        node.sdo.download(0x1A00, 1, struct.pack("<I", 0x60650020))


def test_base_node_402_state_machine_and_csp_motion(rig):
    drives, net = rig
    nodes = [_setup_master(net, n) for n in (1, 2)]
    net.sync.start(0.01)
    for node in nodes:
        node.rpdo[1].start(0.01)
        node.nmt.state = "OPERATIONAL"
    for node in nodes:
        node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
        assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION"
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"
    assert all(d.state == drv.OPERATION_ENABLED for d in drives.drives.values())
    start = time.monotonic()
    goal = {1: 30_000, 2: -20_000}
    while (t := time.monotonic() - start) < 0.6:
        for node in nodes:
            node.rpdo[1]["Target position"].raw = round(goal[node.id] * min(t / 0.5, 1.0))
        time.sleep(0.01)
    for node in nodes:
        assert wait_until(lambda node=node: abs(drives.drives[node.id].position_counts - goal[node.id]) < 20, 10)
        assert wait_until(lambda node=node: abs(node.tpdo[1]["Position actual value"].raw - goal[node.id]) < 20, 10)
    # Back down the state machine.
    nodes[0].state = "SWITCH ON DISABLED"
    assert drives.drives[1].state == drv.SWITCH_ON_DISABLED
    assert drives.drives[2].state == drv.OPERATION_ENABLED


def _sdo_node(net: canopen.Network, node_id: int):
    return net.add_node(node_id, canopen.ObjectDictionary())


def _cw(node, value: int) -> None:
    node.sdo.download(0x6040, 0, struct.pack("<H", value))


def _enable_via_sdo(node, mode: int) -> None:
    node.sdo.download(0x6060, 0, struct.pack("<b", mode))
    for cw in (0x06, 0x07, 0x0F):
        _cw(node, cw)


def test_profile_position_mode_and_quick_stop(rig):
    drives, net = rig
    node = _sdo_node(net, 1)
    drive = drives.drives[1]
    _enable_via_sdo(node, 1)
    assert drive.state == drv.OPERATION_ENABLED
    node.sdo.download(0x6081, 0, struct.pack("<I", 100_000))
    node.sdo.download(0x607A, 0, struct.pack("<i", 40_000))
    _cw(node, 0x1F)  # new set-point (bit 4 rising edge)
    status = struct.unpack("<H", node.sdo.upload(0x6041, 0))[0]
    assert status & 0x1000  # set-point acknowledged
    _cw(node, 0x0F)
    assert wait_until(lambda: abs(drive.position_counts - 40_000) < 20, 10)
    assert wait_until(lambda: struct.unpack("<H", node.sdo.upload(0x6041, 0))[0] & 0x0400, 10)  # target reached
    # Start a long move, then quick stop: the drive decelerates, then (option 2) switch on disabled.
    node.sdo.download(0x607A, 0, struct.pack("<i", -400_000))
    _cw(node, 0x1F)
    assert wait_until(lambda: abs(drive.velocity_counts) > 90_000, 10)
    _cw(node, 0x0B)  # quick stop
    assert drive.state == drv.QUICK_STOP_ACTIVE
    assert wait_until(lambda: drive.state == drv.SWITCH_ON_DISABLED, 10)
    assert abs(drive.velocity_counts) < 1000
    assert drive.position_counts > -400_000 + 100_000  # stopped well before the target


def test_a_quick_stop_ramp_ends_at_the_software_position_limit(rig):
    drives, net = rig
    node = _sdo_node(net, 1)
    drive = drives.drives[1]
    node.sdo.download(0x607D, 1, struct.pack("<i", -50_000))
    node.sdo.download(0x607D, 2, struct.pack("<i", 50_000))
    node.sdo.download(0x6085, 0, struct.pack("<I", 20_000))  # a gentle quick-stop deceleration: a long ramp
    _enable_via_sdo(node, 1)
    node.sdo.download(0x6081, 0, struct.pack("<I", 100_000))
    node.sdo.download(0x6083, 0, struct.pack("<I", 10_000_000))  # reach speed at once, brake late
    node.sdo.download(0x6084, 0, struct.pack("<I", 10_000_000))
    node.sdo.download(0x607A, 0, struct.pack("<i", 49_000))  # inside the limits
    _cw(node, 0x1F)
    assert wait_until(lambda: drive.position_counts > 30_000 and drive.velocity_counts > 90_000, 10)
    _cw(node, 0x0B)  # quick stop at speed: unclamped, the ramp would run ~250,000 counts further
    assert wait_until(lambda: drive.state == drv.SWITCH_ON_DISABLED, 10)
    # stopped at the limit, give or take the motor's overshoot when its demand stops there at full speed (a few
    # hundred counts; ~250,000 counts further without the limit)
    assert drive.position_counts <= 50_000 + 3_000


def test_quick_stop_option_6_holds_and_resumes(rig):
    drives, net = rig
    node = _sdo_node(net, 2)
    drive = drives.drives[2]
    node.sdo.download(0x605A, 0, struct.pack("<h", 6))
    _enable_via_sdo(node, 8)
    _cw(node, 0x0B)
    assert drive.state == drv.QUICK_STOP_ACTIVE
    time.sleep(0.05)
    assert drive.state == drv.QUICK_STOP_ACTIVE  # option 6: stay in quick stop, holding
    assert struct.unpack("<H", node.sdo.upload(0x6041, 0))[0] & 0x6F == 0x07
    _cw(node, 0x0F)  # transition 16
    assert drive.state == drv.OPERATION_ENABLED
    _cw(node, 0x00)
    assert drive.state == drv.SWITCH_ON_DISABLED


def test_fault_emcy_and_reset_on_rising_edge(rig):
    drives, net = rig
    node = _sdo_node(net, 2)
    drive = drives.drives[2]
    emcy: list[int] = []
    node.emcy.add_callback(lambda e: emcy.append(e.code))
    _enable_via_sdo(node, 8)
    drives.inject("drive_fault", device=2, code=0x2310)
    assert wait_until(lambda: drive.state == drv.FAULT, 10)
    assert wait_until(lambda: 0x2310 in emcy, 10)
    assert struct.unpack("<H", node.sdo.upload(0x603F, 0))[0] == 0x2310
    assert node.sdo.upload(0x1001, 0)[0] & 0x03 == 0x03  # generic + current
    _cw(node, 0x80)  # rising edge of bit 7 resets
    assert drive.state == drv.SWITCH_ON_DISABLED
    assert struct.unpack("<H", node.sdo.upload(0x603F, 0))[0] == 0
    drives.inject("drive_fault", device=2, code=0x4310)
    assert wait_until(lambda: drive.state == drv.FAULT, 10)
    _cw(node, 0x80)  # bit 7 already high: no edge, still faulted
    assert drive.state == drv.FAULT
    _cw(node, 0x00)
    _cw(node, 0x80)
    assert drive.state == drv.SWITCH_ON_DISABLED


def test_following_error_faults_with_emcy_8611(rig):
    drives, net = rig
    node = _sdo_node(net, 1)
    drive = drives.drives[1]
    emcy: list[int] = []
    node.emcy.add_callback(lambda e: emcy.append(e.code))
    _enable_via_sdo(node, 8)
    drives.inject("following_error", device=1, counts=20_000)
    assert wait_until(lambda: drive.state == drv.FAULT, 10)
    assert wait_until(lambda: drv.EMCY_FOLLOWING_ERROR in emcy, 10)
    drives.inject("release", device=1)
    assert not drive.jammed


def test_sync_pdo_exchange_and_corrupted_rpdo(rig):
    drives, net = rig
    node = _sdo_node(net, 1)
    drive = drives.drives[1]
    frames: list[bytes] = []
    emcy: list[int] = []
    net.subscribe(0x381, lambda _id, data, _ts: frames.append(bytes(data)))
    node.emcy.add_callback(lambda e: emcy.append(e.code))
    _enable_via_sdo(node, 8)
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: drive.nmt_state == "OPERATIONAL", 10, "the drive in NMT OPERATIONAL (PDOs processed)")
    net.send_message(0x401, struct.pack("<Hi", 0x0F, 500))  # RPDO3 default: controlword + target, sync
    time.sleep(0.02)
    assert drive._target != 500  # synchronous RPDO waits for the SYNC
    net.send_message(0x80, b"")
    assert wait_until(lambda: len(frames) >= 1, 10)
    assert wait_until(lambda: abs(drive.position_counts - 500) < 5, 10)
    net.send_message(0x80, b"")
    assert wait_until(lambda: len(frames) >= 2, 10)
    status, position = struct.unpack("<Hi", frames[-1])
    assert status & 0x6F == 0x27 and abs(position - 500) < 5
    net.send_message(0x401, b"\x0f\x00\x01")  # too short: EMCY 0x8210, not applied
    assert wait_until(lambda: drv.EMCY_PDO_LENGTH in emcy, 10)
    assert drive.state == drv.OPERATION_ENABLED


def test_tpdo_payloads_are_what_the_object_dictionary_reads(rig):
    """A TPDO's payload (its variables looked up once per layout) is the node's own ``get_data`` of every mapped
    entry, for the default layouts and for one remapped by SDO (a stored value among the callback-read ones)."""
    drives, net = rig
    node = _sdo_node(net, 1)
    drive = drives.drives[1]
    _enable_via_sdo(node, 8)
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: drive.nmt_state == "OPERATIONAL", 10, "the drive in NMT OPERATIONAL (PDOs processed)")

    def check() -> int:
        with drive._lock:  # the values do not move between the two reads
            if drive._pdo_dirty:
                drive._reload_pdos()
            pdos = [p for p in drive._tpdos if p.valid and p.entries]
            for pdo in pdos:
                assert drive._tpdo_payload(pdo) == b"".join(drive.node.get_data(i, s) for i, s, _ in pdo.entries)
        return len(pdos)

    assert check() >= 2
    node.nmt.state = "PRE-OPERATIONAL"
    node.sdo.download(0x1A01, 0, b"\x00")
    for sub, entry in enumerate((0x607A0020, 0x60410010, 0x60610008), start=1):  # 0x607A: a stored value
        node.sdo.download(0x1A01, sub, struct.pack("<I", entry))
    node.sdo.download(0x1A01, 0, b"\x03")
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: drive.nmt_state == "OPERATIONAL", 10, "the drive in NMT OPERATIONAL again")
    assert check() >= 2
    remapped = next(p for p in drive._tpdos if p.number == 2)
    assert [e[0] for e in remapped.entries] == [0x607A, 0x6041, 0x6061]


def test_link_faults_drop_and_corrupt_frames(rig):
    drives, net = rig
    received: list[bytes] = []
    net.subscribe(0x701, lambda _id, data, _ts: received.append(bytes(data)))
    assert wait_until(lambda: len(received) >= 2, 10)
    drives.inject("frames", drop=1.0, device=1)
    counts = drives.network.impairment.counts
    # two heartbeats dropped since: one sent before the injection has arrived by now
    wait_until(lambda: counts["dropped"] >= 2, 10, "two frames dropped")
    received.clear()
    wait_until(lambda: counts["dropped"] >= 7, 10, "five more frames dropped")
    assert received == []
    drives.inject("frames", corrupt=1.0, device=1)
    assert wait_until(lambda: len(received) >= 2, 10)
    assert all(len(r) == 0 for r in received)  # one byte short
    drives.inject("frames", delay_ms=50, device=1)
    time.sleep(0.03)
    received.clear()
    t0 = time.monotonic()
    assert wait_until(lambda: len(received) >= 1, 10)
    assert time.monotonic() - t0 >= 0.02
    drives.inject("clear")
    received.clear()
    assert wait_until(lambda: len(received) >= 2, 10)
    assert all(r == b"\x7f" for r in received)
    with pytest.raises(ValueError, match="drop"):
        drives.inject("frames", drop=2.0)
    with pytest.raises(ValueError, match="unknown fault"):
        drives.inject("explode", device=1)


def test_drive_set_rejects_bad_node_ids():
    with pytest.raises(ValueError, match=r"1\.\.127"):
        DriveSet([0, 1])


def test_physics_keeps_running_without_master():
    """Ground truth moves by itself in simulated time (coasting after a push)."""
    channel = _channel()
    with DriveSet([3], channel=channel) as drives:
        drive = drives.drives[3]
        drive._motor.velocity = 1000.0
        assert wait_until(lambda: drive.velocity_counts < 500, 10)
        assert drive.position_counts > 10
    bus = can.Bus(interface="virtual", channel=channel)
    bus.shutdown()


def test_drive_set_says_when_it_cannot_keep_its_physics_rate(monkeypatch, caplog):
    """A stalled physics thread (here: its lock held, as a process waiting for a CPU) is reported with the achieved
    rate, not slipped silently."""
    from sim_hardware.canopen import network

    monkeypatch.setattr(network, "RATE_WINDOW_S", 0.2)
    caplog.set_level("WARNING", logger="sim_hardware.canopen.network")
    with DriveSet([1], channel=_channel()) as drives:
        assert wait_until(lambda: drives.rate_report()["achieved_hz"] > 0 and drives._rate.windows_behind == 0
                          and drives._rate.stepped > 50, 5, "a first window")
        with drives._physics_lock:
            time.sleep(0.12)
        assert wait_until(lambda: drives.rate_report()["windows_behind"] >= 1, 5, "a window that fell behind")
        report = drives.rate_report()
        assert report["max_late_ms"] >= 100 or report["dropped_steps"] >= 50
        assert report["achieved_hz"] < 0.95 * report["physics_hz"]
    assert any("behind its 1000 Hz physics rate: achieved" in r.getMessage() for r in caplog.records)


def test_direct_transport_serves_a_master_over_socketcand():
    """The emulator's own set-up (drives delivered by the socketcand server, no python-can bus between them): canopen's
    master configures a drive over SDO and reads its TPDOs through python-can's socketcand client."""
    from sim_hardware.socketcand import SocketcandServer

    drives = DriveSet([4])
    server = SocketcandServer(on_frame=drives.deliver, port=0)
    drives.start(transport=server.publish)
    server.start()
    net = canopen.Network()
    try:
        net.connect(interface="socketcand", host=server.host, port=server.port, channel="can0")
        node = net.add_node(4, build_od(4))
        assert node.sdo[0x1000].raw == DEVICE_TYPE
        node.sdo[0x6060].raw = 8
        assert drives.drives[4]._mode == 8
        assert wait_until(lambda: server.frames_to_bus >= 2 and server.frames_from_bus >= 2, 5, "frames both ways")
    finally:
        net.disconnect()
        server.stop()
        drives.stop()
