"""``canopen402``: CiA 402 servo drives in cyclic synchronous position mode over CANopen.

Works on any python-can interface. Options (bus ``options`` in the head config):

``interface`` (required), ``channel`` (default ``can0``), ``bitrate`` (default 1000000),
``host``/``port`` (socketcand only; port required there), ``bus_options`` (extra ``can.Bus`` keyword
arguments), ``heartbeat_period_s`` (the drives' producer time, written to 0x1017; default 0.05, or a quarter of
the timeout when only that is given), ``heartbeat_timeout_s`` (default two periods; a lost heartbeat faults the bus
at most one monitor tick, ≤ 20 ms, after it),
``node_timeout_s`` (1.0, how long open waits for each node), ``sdo_timeout_s`` (0.3),
``state_timeout_s`` (0.5, per CiA 402 transition), ``feedback_timeout_s`` (0.1) and ``stale_cycles`` (3)
(feedback is stale when a drive missed that many SYNCs *and* that much time), ``cycle_period_s``
(optional, written to the interpolation period 0x60C2), ``following_error_window_counts``
(optional, 0x6065), ``tpdo2_every`` (1: TPDO2 on every SYNC; N: on every Nth, its transmission type 0x1801:02 — at
a high loop rate velocity, current and error code need not ride every cycle, and each TPDO2 is a frame per drive
that the bus, and every process on its way, carries).

What open does per node: wait for an SDO answer (a silent node raises :class:`BusTimeout` naming
the motor after ``node_timeout_s``), check the CiA 402 device type, NMT pre-operational, heartbeat
producer time, PDOs (RPDO1 = controlword + target position; TPDO1 = statusword + position actual,
TPDO2 = velocity actual + current actual + error code, on every SYNC or every ``tpdo2_every``-th; the others
disabled),
mode CSP, NMT operational, and wait for its first operational heartbeat. Cyclic I/O: :meth:`write`
sends every RPDO then one SYNC; :meth:`read` returns the latest TPDO feedback and sends a SYNC itself
when none went out since the previous read, so feedback stays fresh while inactive. A motor state's timestamp is
when its drive's latest TPDO1 was on the bus (:class:`FrameClock`), not when this process got to it.

Faults (all end in FAULT through :meth:`mark_fault`, then a quick stop of every drive): EMCY from a
drive (its code; length/overrun EMCYs 0x8110/0x8120/0x8210/0x8220 are only counted), a drive's
statusword in FAULT (code from 0x603F), and the driver's own codes :data:`FAULT_HEARTBEAT_LOST`,
:data:`FAULT_NODE_STATE`, :data:`FAULT_FEEDBACK_STALE`, :data:`FAULT_LEFT_ENABLED`. Dropped or
malformed (wrong-length) TPDOs are counted in :meth:`diagnostics` and the previous sample is kept
until feedback goes stale. Callbacks on the bus thread never take the bus lock: they queue events
that the monitor thread, :meth:`read` or :meth:`write` turn into faults.

In-process use with emulated drives (one process, python-can ``virtual`` bus)::

    from sim_hardware.canopen.network import DriveSet
    with DriveSet(range(1, 8), channel="likeness-sample-can0"):
        bus = CanOpen402Bus("can0", {"interface": "virtual", "channel": "likeness-sample-can0"}, motors)
        bus.open(); bus.enable(); bus.write({...}); bus.read(); bus.close()

Across processes, serve the drives with ``likeness sim canopen --port P`` and use options
``{"interface": "socketcand", "host": "127.0.0.1", "port": P, "channel": "can0"}``.
"""

from __future__ import annotations

import collections
import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import can
import canopen
from can.interfaces.socketcand import SocketCanDaemonBus as _SocketcandBus
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.base import LifecycleState, MotorBus, MotorConfig, MotorState
from drivers.errors import BusInitError, BusTimeout, ConfigError, DeviceFault

log = logging.getLogger(__name__)

#: Driver-side fault codes (CiA 301 communication class, 0x813x reserved here for this driver).
FAULT_HEARTBEAT_LOST = 0x8130  # CiA 301: life guard / heartbeat error
DEFAULT_HEARTBEAT_PERIOD_S = 0.05
HEARTBEAT_TIMEOUT_PERIODS = 2.0  # default consumer timeout, in producer periods
FAULT_NODE_STATE = 0x8131  # node rebooted or left NMT OPERATIONAL
FAULT_FEEDBACK_STALE = 0x8132  # no TPDO feedback for stale_cycles SYNCs and feedback_timeout_s
FAULT_LEFT_ENABLED = 0x8133  # drive left OPERATION ENABLED without reporting a fault
FAULT_UNKNOWN = 0xFF00  # drive in FAULT but no error code available

#: EMCY codes that are counted, not escalated: CAN overrun, error passive, PDO length errors.
TOLERATED_EMCY = frozenset({0x8110, 0x8120, 0x8210, 0x8220})

CW_DISABLE_VOLTAGE, CW_QUICK_STOP, CW_SHUTDOWN = 0x00, 0x02, 0x06
CW_SWITCH_ON, CW_ENABLE, CW_FAULT_RESET = 0x07, 0x0F, 0x80
MODE_CSP = 8
NMT_OPERATIONAL = 5

_STATES = (  # (mask, value, name), CiA 402 statusword decoding
    (0x4F, 0x08, "FAULT"),
    (0x4F, 0x0F, "FAULT REACTION ACTIVE"),
    (0x4F, 0x00, "NOT READY TO SWITCH ON"),
    (0x4F, 0x40, "SWITCH ON DISABLED"),
    (0x6F, 0x21, "READY TO SWITCH ON"),
    (0x6F, 0x23, "SWITCHED ON"),
    (0x6F, 0x27, "OPERATION ENABLED"),
    (0x6F, 0x07, "QUICK STOP ACTIVE"),
)
_TORQUE_ON = ("OPERATION ENABLED", "QUICK STOP ACTIVE", "FAULT REACTION ACTIVE")

_TPDO1 = struct.Struct("<Hi")  # statusword, position actual
_TPDO2 = struct.Struct("<ihH")  # velocity actual, current actual (per mille), error code
_RPDO1 = struct.Struct("<Hi")  # controlword, target position


#: A frame that seems older than this is not believed (a clock step): it counts as just received.
MAX_FRAME_AGE_S = 10.0
#: How long the transport's shortest delay is remembered (two windows of this; a clock step is forgotten after).
DELAY_FLOOR_WINDOW_S = 5.0


class FrameClock:
    """When a frame was on the bus, as ``time.monotonic()``, from its python-can stamp (wall-clock seconds: the
    kernel's receive time on SocketCAN, the server's on socketcand), so that a backlog of frames read late still shows
    when the drives sent them. A remote server's clock may differ from this host's: ages count from the shortest
    delay seen lately (the transport at its quickest), so a constant offset cancels out."""

    def __init__(self) -> None:
        self._floor = math.inf  # shortest delay in the current window
        self._floor_before = math.inf  # ... and in the window before
        self._window_end = 0.0

    def reported_at(self, frame_time: float) -> float:
        """The monotonic time at which a frame stamped ``frame_time`` was on the bus (now when implausible)."""
        now = time.monotonic()
        delay = time.time() - frame_time
        if not math.isfinite(delay) or frame_time <= 0.0:
            return now
        if now >= self._window_end:
            self._floor_before, self._floor = self._floor, math.inf
            self._window_end = now + DELAY_FLOOR_WINDOW_S
        self._floor = min(self._floor, delay)
        age = delay - min(self._floor, self._floor_before)
        return now - age if age < MAX_FRAME_AGE_S else now


class _QuietPartialReads(logging.Filter):
    """Drop python-can's socketcand client warning about a message split across TCP reads (benign, per read)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Got incomplete message")


_SOCKETCAND_LOG = logging.getLogger("can.interfaces.socketcand.socketcand")
if not any(isinstance(f, _QuietPartialReads) for f in _SOCKETCAND_LOG.filters):
    _SOCKETCAND_LOG.addFilter(_QuietPartialReads())


def send_frames(net: canopen.Network, frames: Sequence[tuple[int, bytes]]) -> None:
    """Send ``frames`` (11-bit COB-ID, data) on ``net`` in order. Over socketcand they go as one TCP write of the
    bridge's ASCII commands: python-can writes each frame on its own (a system call, a wake-up of the bridge and a
    formatted debug line per frame), and a cycle's seven RPDOs and SYNC took 160-220 µs that way. Other interfaces
    take them one by one, as the CAN controller does anyway."""
    bus = net.bus
    tcp_send = getattr(bus, "_tcp_send", None) if isinstance(bus, _SocketcandBus) else None
    if tcp_send is None:
        for cob_id, data in frames:
            net.send_message(cob_id, data)
        return
    text = "".join(f"< send {cob_id:03X} {len(data):X} {data.hex(' ')} >" for cob_id, data in frames)
    with net.send_lock:  # canopen's own sends (SDO, NMT) take the same lock
        tcp_send(text)
    net.check()


def _where(index: int, subindex: int) -> str:
    return f"0x{index:04X}:{subindex}"


def state_name(statusword: int) -> str:
    """CiA 402 state name of a statusword (``"UNKNOWN"`` if it matches none)."""
    for mask, value, name in _STATES:
        if statusword & mask == value:
            return name
    return "UNKNOWN"


@dataclass(frozen=True, slots=True)
class _Options:
    interface: str
    channel: str
    bitrate: int
    host: str
    port: int | None
    bus_options: dict[str, Any]
    heartbeat_timeout_s: float
    heartbeat_period_s: float
    node_timeout_s: float
    sdo_timeout_s: float
    state_timeout_s: float
    feedback_timeout_s: float
    stale_cycles: int
    cycle_period_s: float | None
    following_error_window_counts: int | None
    tpdo2_every: int


def _parse_options(bus: str, options: Mapping[str, Any]) -> _Options:
    known = set(_Options.__dataclass_fields__)

    def err(key: str, message: str) -> ConfigError:
        return ConfigError(key, f"bus {bus!r}: {message}")

    for key in options:
        if key not in known:
            raise err(key, f"unknown canopen402 option; known: {', '.join(sorted(known))}")

    def number(key: str, default: float | None, *, positive: bool = True, integer: bool = False) -> Any:
        value = options.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise err(key, f"must be a finite number, got {value!r}")
        if integer and value != int(value):
            raise err(key, f"must be an integer, got {value!r}")
        if positive and value <= 0:
            raise err(key, f"must be positive, got {value!r}")
        return int(value) if integer else float(value)

    def text(key: str, default: str | None) -> str | None:
        value = options.get(key, default)
        if value is not None and (not isinstance(value, str) or not value):
            raise err(key, f"must be a non-empty string, got {value!r}")
        return value

    interface = text("interface", None)
    if interface is None:
        raise err("interface", "required (a python-can interface name, e.g. 'socketcand', 'socketcan', 'virtual')")
    port = number("port", None, integer=True)
    if interface == "socketcand" and port is None:
        raise err("port", "required with interface 'socketcand'")
    if port is not None and not 0 < port < 65536:
        raise err("port", f"must be 1..65535, got {port}")
    bus_options = options.get("bus_options", {})
    if not isinstance(bus_options, Mapping):
        raise err("bus_options", f"must be a table of can.Bus keyword arguments, got {bus_options!r}")
    given_timeout = number("heartbeat_timeout_s", None)
    hb_period = number("heartbeat_period_s", DEFAULT_HEARTBEAT_PERIOD_S if given_timeout is None else given_timeout / 4)
    hb_timeout = given_timeout if given_timeout is not None else HEARTBEAT_TIMEOUT_PERIODS * hb_period
    if hb_period >= hb_timeout:
        raise err("heartbeat_period_s", f"must be below heartbeat_timeout_s ({hb_period} >= {hb_timeout})")
    if not 0.001 <= hb_period <= 65.535:
        raise err("heartbeat_period_s", f"must be 0.001..65.535 s (0x1017 is in ms), got {hb_period}")
    cycle = number("cycle_period_s", None)
    if cycle is not None and not 0.001 <= cycle <= 0.255:
        raise err("cycle_period_s", f"must be 0.001..0.255 s (0x60C2 in ms), got {cycle}")
    window = number("following_error_window_counts", None, integer=True)
    tpdo2_every = number("tpdo2_every", 1, integer=True)
    if not 1 <= tpdo2_every <= 240:
        raise err("tpdo2_every", f"must be 1..240 SYNCs (a synchronous transmission type), got {tpdo2_every}")
    return _Options(
        interface=interface,
        channel=text("channel", "can0"),
        bitrate=number("bitrate", 1_000_000, integer=True),
        host=text("host", "127.0.0.1"),
        port=port,
        bus_options=dict(bus_options),
        heartbeat_timeout_s=hb_timeout,
        heartbeat_period_s=hb_period,
        node_timeout_s=number("node_timeout_s", 1.0),
        sdo_timeout_s=number("sdo_timeout_s", 0.3),
        state_timeout_s=number("state_timeout_s", 0.5),
        feedback_timeout_s=number("feedback_timeout_s", 0.1),
        stale_cycles=number("stale_cycles", 3, integer=True),
        cycle_period_s=cycle,
        following_error_window_counts=window,
        tpdo2_every=tpdo2_every,
    )


class _Node:
    """Per-drive bookkeeping: latest feedback (written by the bus thread) and the RPDO image."""

    def __init__(self, motor: MotorConfig, node: canopen.RemoteNode) -> None:
        self.motor = motor
        self.node = node
        self.id = motor.device_id
        self.status = 0
        self.position = 0
        self.velocity = 0
        self.current = 0
        self.error_code = 0
        self.emcy_code = 0
        self.stamp = 0.0  # monotonic time of the latest valid TPDO1
        self.answered_sync = 0  # SYNC counter when the latest TPDO1 arrived
        self.answered_sync2 = 0  # same for TPDO2
        self.last_heartbeat = 0.0
        self.nmt_state = -1
        self.expect_operational = False
        self.heartbeat_lost = False
        self.target = 0
        self.controlword = CW_DISABLE_VOLTAGE
        self.rated_current_a = math.nan
        self.malformed = 0


class CanOpen402Bus(MotorBus):
    """CiA 402 drives in CSP mode on one CAN bus (see the module docstring for options and faults)."""

    driver_name: ClassVar[str] = "canopen402"

    def __init__(self, name: str, options: Mapping[str, Any], motors: Sequence[MotorConfig]) -> None:
        super().__init__(name, options, motors)
        self._opts = _parse_options(name, self.options)
        for motor in self._motors.values():
            if not 1 <= motor.device_id <= 127:
                raise ConfigError(
                    f"motor {motor.name!r}.device_id", f"CANopen node id must be 1..127, got {motor.device_id}"
                )
        self._network: canopen.Network | None = None
        self._nodes: dict[str, _Node] = {}
        self._events: collections.deque[tuple[str, int, str]] = collections.deque()
        self._sync_count = 0
        self._synced_since_read = False
        self._enable_sync = 0
        self._monitor: threading.Thread | None = None
        self._monitor_stop = threading.Event()
        self._stats = {"syncs": 0, "malformed_tpdos": 0, "tolerated_emcy": 0, "emcy": 0}
        self._feedback = threading.Event()
        self._frame_clock = FrameClock()  # TPDO stamps (used on the bus thread only)

    # ------------------------------------------------------------------ diagnostics
    def wait_for_feedback(self, timeout_s: float) -> bool:
        """Block (without the bus lock) until every drive answered the latest SYNC; False on timeout.

        For loops that want the feedback of this cycle's SYNC before the next read, and for
        latency measurements; the normal loop just reads the latest sample.
        """
        return self._feedback.wait(timeout_s)

    def diagnostics(self) -> dict[str, Any]:
        """Counters (SYNCs sent, malformed TPDOs, EMCYs) and per-node feedback age in seconds."""
        now = time.monotonic()
        return {
            **self._stats,
            "feedback_age_s": {n.motor.name: now - n.stamp for n in self._nodes.values()},
            "drive_states": {n.motor.name: state_name(n.status) for n in self._nodes.values()},
        }

    # ------------------------------------------------------------------ open / close
    def _connect(self) -> canopen.Network:
        o = self._opts
        kwargs: dict[str, Any] = {"interface": o.interface, "channel": o.channel}
        if o.interface == "socketcand":
            self._probe_tcp(o.host, o.port)
            kwargs.update(host=o.host, port=o.port, tcp_tune=True)
        else:
            kwargs["bitrate"] = o.bitrate
        kwargs.update(o.bus_options)
        try:
            bus = can.Bus(**kwargs)
        except Exception as exc:  # python-can raises many types for a bad interface or channel
            raise BusInitError(f"bus {self.name!r}: cannot open {o.interface} channel {o.channel!r}: {exc}") from exc
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.1  # bounded shutdown time
        network.connect()
        return network

    def _probe_tcp(self, host: str, port: int | None) -> None:
        """Fail fast when no socketcand server listens (python-can's client retries for 10 s)."""
        try:
            with socket.create_connection((host, port), timeout=self._opts.node_timeout_s):
                pass
        except OSError as exc:
            raise BusInitError(f"bus {self.name!r}: no socketcand server at {host}:{port}: {exc}") from exc

    def _open(self) -> None:
        self._events.clear()
        self._network = self._connect()
        try:
            for motor in self._motors.values():
                remote = canopen.RemoteNode(motor.device_id, canopen.ObjectDictionary())
                remote.sdo.RESPONSE_TIMEOUT = self._opts.sdo_timeout_s
                node = _Node(motor, remote)
                self._network.add_node(remote)
                self._subscribe(node)
                self._nodes[motor.name] = node
            for node in self._nodes.values():
                self._wait_for_node(node)
            for node in self._nodes.values():
                node.node.nmt.state = "PRE-OPERATIONAL"
                self._configure(node)
            self._go_operational(list(self._nodes.values()))
            self._start_monitor()
        except BaseException:
            self._close()
            raise

    def _subscribe(self, node: _Node) -> None:
        net = self._network
        assert net is not None
        net.subscribe(0x180 + node.id, lambda _id, data, ts, n=node: self._on_tpdo1(n, data, ts))
        net.subscribe(0x280 + node.id, lambda _id, data, _ts, n=node: self._on_tpdo2(n, data))
        node.node.emcy.add_callback(lambda entry, n=node: self._on_emcy(n, entry))
        node.node.nmt.add_heartbeat_callback(lambda state, n=node: self._on_heartbeat(n, state))

    def _wait_for_node(self, node: _Node) -> None:
        deadline = time.monotonic() + self._opts.node_timeout_s
        sdo = node.node.sdo
        while True:
            try:
                device_type = struct.unpack("<I", sdo.upload(0x1000, 0)[:4].ljust(4, b"\0"))[0]
                break
            except SdoCommunicationError:
                if time.monotonic() >= deadline:
                    raise BusTimeout(
                        node.motor.name,
                        f"CANopen node {node.id} on bus {self.name!r} did not answer "
                        f"(no boot-up, heartbeat or SDO response in {self._opts.node_timeout_s:g} s)",
                    ) from None
            except SdoAbortedError as exc:
                raise BusInitError(f"{node.motor.name}: node {node.id} refused reading the device type: {exc}") from exc
        if device_type & 0xFFFF != 402:
            raise BusInitError(
                f"{node.motor.name}: node {node.id} is not a CiA 402 drive (device type 0x{device_type:08X})"
            )

    def _sdo_write(self, node: _Node, index: int, subindex: int, fmt: str, value: int) -> None:
        try:
            node.node.sdo.download(index, subindex, struct.pack(fmt, value))
        except SdoCommunicationError as exc:
            where = _where(index, subindex)
            raise BusTimeout(node.motor.name, f"node {node.id}: no SDO answer writing {where}") from exc
        except SdoAbortedError as exc:
            raise BusInitError(
                f"{node.motor.name}: node {node.id} refused {_where(index, subindex)} = {value}: {exc}"
            ) from exc

    def _sdo_read(self, node: _Node, index: int, subindex: int, fmt: str) -> int:
        try:
            data = node.node.sdo.upload(index, subindex)
        except SdoCommunicationError as exc:
            where = _where(index, subindex)
            raise BusTimeout(node.motor.name, f"node {node.id}: no SDO answer reading {where}") from exc
        except SdoAbortedError as exc:
            raise BusInitError(
                f"{node.motor.name}: node {node.id} refused reading {_where(index, subindex)}: {exc}"
            ) from exc
        size = struct.calcsize(fmt)
        if len(data) < size:
            where = _where(index, subindex)
            raise BusInitError(f"{node.motor.name}: node {node.id} sent {len(data)} bytes for {where}")
        return struct.unpack(fmt, data[:size])[0]

    def _configure(self, node: _Node) -> None:
        """SDO configuration in pre-operational: heartbeat, PDO layout, optional parameters, mode CSP."""
        o, nid, w = self._opts, node.id, self._sdo_write
        w(node, 0x1017, 0, "<H", round(o.heartbeat_period_s * 1000))
        for k in range(4):
            w(node, 0x1400 + k, 1, "<I", 0x80000000 | (0x200 + 0x100 * k + nid))
            w(node, 0x1800 + k, 1, "<I", 0x80000000 | (0x180 + 0x100 * k + nid))
        layouts = (  # comm, mapping, COB-ID base, entries, transmission type (synchronous: every Nth SYNC)
            (0x1400, 0x1600, 0x200, (0x60400010, 0x607A0020), 1),
            (0x1800, 0x1A00, 0x180, (0x60410010, 0x60640020), 1),
            (0x1801, 0x1A01, 0x280, (0x606C0020, 0x60780010, 0x603F0010), o.tpdo2_every),
        )
        for comm, mapping, cob, entries, every in layouts:
            w(node, mapping, 0, "<B", 0)
            for sub, entry in enumerate(entries, start=1):
                w(node, mapping, sub, "<I", entry)
            w(node, mapping, 0, "<B", len(entries))
            w(node, comm, 2, "<B", every)
            w(node, comm, 1, "<I", cob + nid)
        # The drive's own software position limits (0x607D) at the motor's configured limits: a second line of
        # defence behind the driver's checks, and what stops a quick-stop ramp at the end of the travel.
        lo, hi = sorted((node.motor.to_counts(node.motor.min_position), node.motor.to_counts(node.motor.max_position)))
        w(node, 0x607D, 1, "<i", lo)
        w(node, 0x607D, 2, "<i", hi)
        if o.following_error_window_counts is not None:
            w(node, 0x6065, 0, "<I", o.following_error_window_counts)
        if o.cycle_period_s is not None:
            w(node, 0x60C2, 1, "<B", round(o.cycle_period_s * 1000))
            w(node, 0x60C2, 2, "<b", -3)
        if not self._sdo_read(node, 0x6502, 0, "<I") & 0x80:
            raise BusInitError(f"{node.motor.name}: node {nid} does not support cyclic synchronous position mode")
        w(node, 0x6060, 0, "<b", MODE_CSP)
        deadline = time.monotonic() + o.state_timeout_s
        while self._sdo_read(node, 0x6061, 0, "<b") != MODE_CSP:
            if time.monotonic() > deadline:
                raise BusTimeout(node.motor.name, f"node {nid} did not switch to CSP mode (0x6061)")
            time.sleep(0.002)
        try:
            node.rated_current_a = self._sdo_read(node, 0x6075, 0, "<I") / 1000.0
        except BusInitError:
            node.rated_current_a = math.nan  # optional object: effort unknown
        self._seed_feedback(node)

    def _seed_feedback(self, node: _Node) -> None:
        """Fresh feedback by SDO (used at open, enable and reset, when no SYNC may have gone out)."""
        node.status = self._sdo_read(node, 0x6041, 0, "<H")
        node.position = self._sdo_read(node, 0x6064, 0, "<i")
        node.error_code = self._sdo_read(node, 0x603F, 0, "<H")
        node.velocity = 0
        node.stamp = time.monotonic()
        node.answered_sync = self._sync_count

    def _go_operational(self, nodes: list[_Node]) -> None:
        """NMT operational, then wait for each node's first heartbeat reporting it."""
        for node in nodes:
            node.nmt_state = -1
            node.expect_operational = False
            node.node.nmt.state = "OPERATIONAL"
        deadline = time.monotonic() + self._opts.node_timeout_s + self._opts.heartbeat_period_s
        for node in nodes:
            while node.nmt_state != NMT_OPERATIONAL:
                if time.monotonic() > deadline:
                    raise BusTimeout(
                        node.motor.name,
                        f"node {node.id}: no heartbeat reporting OPERATIONAL within {self._opts.node_timeout_s:g} s",
                    )
                time.sleep(0.002)
            node.heartbeat_lost = False
            node.expect_operational = True

    def _close(self) -> None:
        self._monitor_stop.set()
        if self._monitor is not None and self._monitor is not threading.current_thread():
            self._monitor.join(timeout=1.0)
        self._monitor = None
        net, self._network = self._network, None
        if net is not None:
            try:
                for node in self._nodes.values():
                    node.expect_operational = False
                    node.node.nmt.state = "PRE-OPERATIONAL"  # stop PDO processing on the drives
            except Exception as exc:
                log.debug("bus %s: NMT on close failed: %s", self.name, exc)
            try:
                net.disconnect()
            except Exception as exc:
                log.debug("bus %s: disconnect failed: %s", self.name, exc)
        self._nodes.clear()

    # ------------------------------------------------------------------ bus-thread callbacks (no bus lock here)
    def _on_tpdo1(self, node: _Node, data: bytes, frame_time: float) -> None:
        if len(data) != _TPDO1.size:
            node.malformed += 1
            self._stats["malformed_tpdos"] += 1
            return
        node.status, node.position = _TPDO1.unpack(data)
        node.stamp = self._frame_clock.reported_at(frame_time)
        node.answered_sync = self._sync_count
        self._check_cycle_complete()

    def _on_tpdo2(self, node: _Node, data: bytes) -> None:
        if len(data) != _TPDO2.size:
            node.malformed += 1
            self._stats["malformed_tpdos"] += 1
            return
        node.velocity, node.current, node.error_code = _TPDO2.unpack(data)
        node.answered_sync2 = self._sync_count
        self._check_cycle_complete()

    def _check_cycle_complete(self) -> None:
        count = self._sync_count
        every_sync = self._opts.tpdo2_every == 1  # else TPDO2 follows only some SYNCs: TPDO1 completes a cycle
        if all(n.answered_sync >= count and (n.answered_sync2 >= count or not every_sync)
               for n in self._nodes.values()):
            self._feedback.set()

    def _on_emcy(self, node: _Node, entry: Any) -> None:
        code = entry.code
        if code & 0xFF00 == 0:
            return  # error reset / no error
        if code in TOLERATED_EMCY:
            self._stats["tolerated_emcy"] += 1
            log.warning("bus %s: %s sent EMCY 0x%04X (counted, not a fault)", self.name, node.motor.name, code)
            return
        self._stats["emcy"] += 1
        node.emcy_code = code
        desc = entry.get_desc() or "error"
        self._events.append((node.motor.name, code, f"EMCY 0x{code:04X} ({desc}) from node {node.id}"))

    def _on_heartbeat(self, node: _Node, state: int) -> None:
        node.last_heartbeat = time.monotonic()
        node.nmt_state = state
        if node.expect_operational and state != NMT_OPERATIONAL:
            node.expect_operational = False
            what = "rebooted (boot-up message)" if state == 0 else f"left NMT OPERATIONAL (heartbeat state {state})"
            self._events.append((node.motor.name, FAULT_NODE_STATE, f"node {node.id} {what}"))

    # ------------------------------------------------------------------ monitor thread
    def _start_monitor(self) -> None:
        self._monitor_stop.clear()
        self._monitor = threading.Thread(target=self._monitor_loop, name=f"canopen402-{self.name}-monitor", daemon=True)
        self._monitor.start()

    def _monitor_loop(self) -> None:
        period = min(self._opts.heartbeat_timeout_s / 5.0, 0.02)
        while not self._monitor_stop.wait(period):
            now = time.monotonic()
            for node in list(self._nodes.values()):
                if not node.expect_operational or node.heartbeat_lost:
                    continue
                age = now - node.last_heartbeat
                if age > self._opts.heartbeat_timeout_s:
                    node.heartbeat_lost = True
                    self._events.append((
                        node.motor.name,
                        FAULT_HEARTBEAT_LOST,
                        f"no heartbeat from node {node.id} for {age * 1e3:.0f} ms "
                        f"(timeout {self._opts.heartbeat_timeout_s * 1e3:.0f} ms)",
                    ))
            # Never block on the bus lock: close() holds it while joining this thread.
            while self._events and not self._monitor_stop.is_set():
                if self._lock.acquire(timeout=0.05):
                    try:
                        self._drain_events()
                    finally:
                        self._lock.release()

    def _drain_events(self) -> None:
        while self._events:
            try:
                device, code, message = self._events.popleft()
            except IndexError:
                return
            self.mark_fault(device, code, message)

    # ------------------------------------------------------------------ CiA 402 state walking (SDO)
    def _walk(self, nodes: list[_Node], goal: str) -> None:
        """Drive every node to ``goal`` (OPERATION ENABLED, SWITCHED ON or SWITCH ON DISABLED) over SDO."""
        for node in nodes:
            deadline = time.monotonic() + 4 * self._opts.state_timeout_s
            last_cw = None
            while True:
                state = state_name(self._sdo_read(node, 0x6041, 0, "<H"))
                if state == goal or (goal == "SWITCHED ON" and state not in _TORQUE_ON):
                    break
                cw = self._next_controlword(node, state, goal)
                if cw is not None and cw != last_cw:
                    if cw == CW_FAULT_RESET:
                        self._sdo_write(node, 0x6040, 0, "<H", CW_DISABLE_VOLTAGE)  # rising edge of bit 7
                    self._sdo_write(node, 0x6040, 0, "<H", cw)
                    last_cw = cw
                    continue
                if time.monotonic() > deadline:
                    raise BusTimeout(node.motor.name, f"node {node.id} did not reach {goal} (stuck in {state})")
                time.sleep(0.002)

    def _next_controlword(self, node: _Node, state: str, goal: str) -> int | None:
        if goal == "OPERATION ENABLED":
            if state in ("FAULT", "FAULT REACTION ACTIVE"):
                code = node.error_code or node.emcy_code or FAULT_UNKNOWN
                raise DeviceFault(node.motor.name, code, f"node {node.id} is in {state}; reset the fault first")
            return {
                "SWITCH ON DISABLED": CW_SHUTDOWN,
                "READY TO SWITCH ON": CW_SWITCH_ON,
                "SWITCHED ON": CW_ENABLE,
                "QUICK STOP ACTIVE": CW_DISABLE_VOLTAGE,
            }.get(state)
        if goal == "SWITCHED ON":
            return CW_SWITCH_ON if state == "OPERATION ENABLED" else None
        # SWITCH ON DISABLED
        if state == "FAULT":
            return CW_FAULT_RESET
        if state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED", "QUICK STOP ACTIVE"):
            return CW_DISABLE_VOLTAGE
        return None

    # ------------------------------------------------------------------ lifecycle hooks
    def _enable(self) -> None:
        nodes = list(self._nodes.values())
        for node in nodes:
            node.position = self._sdo_read(node, 0x6064, 0, "<i")
            node.target = node.position
            self._sdo_write(node, 0x607A, 0, "<i", node.target)
        try:
            self._walk(nodes, "OPERATION ENABLED")
        except BaseException:
            try:
                self._walk(nodes, "SWITCHED ON")
            except Exception:
                log.exception("bus %s: could not disable after a failed enable", self.name)
            raise
        for node in nodes:
            node.controlword = CW_ENABLE
            self._seed_feedback(node)
        self._enable_sync = self._sync_count

    def _disable(self) -> None:
        for node in self._nodes.values():
            node.controlword = CW_SWITCH_ON
        self._walk(list(self._nodes.values()), "SWITCHED ON")
        for node in self._nodes.values():
            self._seed_feedback(node)

    def _on_fault(self) -> None:
        """Safe state without waiting: quick stop to every drive by RPDO + SYNC (drives ramp down, torque off)."""
        net = self._network
        if net is None:
            return
        for node in self._nodes.values():
            node.controlword = CW_QUICK_STOP
        self._count_sync()
        send_frames(net, [*((0x200 + n.id, _RPDO1.pack(CW_QUICK_STOP, n.target)) for n in self._nodes.values()),
                          (0x80, b"")])

    def _reset_fault(self) -> None:
        self._events.clear()
        now = time.monotonic()
        nodes = list(self._nodes.values())
        for node in nodes:
            if now - node.last_heartbeat > self._opts.heartbeat_timeout_s:
                raise BusTimeout(node.motor.name, f"node {node.id}: no heartbeat, cannot reset the fault")
        rebooted = [n for n in nodes if n.nmt_state != NMT_OPERATIONAL]
        for node in rebooted:
            node.expect_operational = False
            node.node.nmt.state = "PRE-OPERATIONAL"
            self._configure(node)
        if rebooted:
            self._go_operational(rebooted)
        self._walk(nodes, "SWITCH ON DISABLED")
        for node in nodes:
            node.controlword = CW_DISABLE_VOLTAGE
            node.emcy_code = 0
            node.heartbeat_lost = False
            node.expect_operational = True
            self._seed_feedback(node)
            node.target = node.position
        self._events.clear()

    # ------------------------------------------------------------------ cyclic I/O
    def _send_sync(self) -> None:
        assert self._network is not None
        self._count_sync()
        self._network.send_message(0x80, b"")

    def _count_sync(self) -> None:
        """The bookkeeping of a SYNC about to be sent: the feedback of the next cycle is awaited from now."""
        self._sync_count += 1
        self._stats["syncs"] += 1
        self._synced_since_read = True
        self._feedback.clear()

    def _write(self, targets: Mapping[str, float]) -> None:
        self._drain_events()
        if self._state is LifecycleState.FAULT:
            device, (code, message) = next(iter(self._faults.items()))
            raise DeviceFault(device, code, f"bus {self.name!r} is in FAULT ({message})")
        net = self._network
        assert net is not None
        for name, value in targets.items():
            node = self._nodes[name]
            node.target = node.motor.to_counts(value)
        frames = [(0x200 + node.id, _RPDO1.pack(node.controlword, node.target)) for node in self._nodes.values()]
        self._count_sync()
        send_frames(net, [*frames, (0x80, b"")])  # the RPDOs, then the SYNC that applies them

    def _read(self) -> dict[str, MotorState]:
        self._drain_events()
        now = time.monotonic()
        o = self._opts
        for node in self._nodes.values():
            state = state_name(node.status)
            if state in ("FAULT", "FAULT REACTION ACTIVE"):
                code = node.error_code or node.emcy_code or FAULT_UNKNOWN
                if node.motor.name not in self._faults:
                    self.mark_fault(node.motor.name, code, f"node {node.id} reports {state} (error code 0x{code:04X})")
            elif (
                self._state is LifecycleState.ACTIVE
                and node.answered_sync > self._enable_sync
                and state != "OPERATION ENABLED"
            ):
                self.mark_fault(node.motor.name, FAULT_LEFT_ENABLED, f"node {node.id} left OPERATION ENABLED ({state})")
            if (
                self._state is not LifecycleState.FAULT
                and self._sync_count - node.answered_sync >= o.stale_cycles
                and now - node.stamp > o.feedback_timeout_s
            ):
                self.mark_fault(
                    node.motor.name,
                    FAULT_FEEDBACK_STALE,
                    f"no feedback from node {node.id} for {self._sync_count - node.answered_sync} SYNCs "
                    f"({(now - node.stamp) * 1e3:.0f} ms)",
                )
        states = {}
        for name, node in self._nodes.items():
            m = node.motor
            code = self._faults.get(name, (0, ""))[0]
            states[name] = MotorState(
                position=m.from_counts(node.position),
                velocity=m.velocity_from_counts(node.velocity),
                effort=node.current / 1000.0 * node.rated_current_a,
                status=node.status,
                fault_code=code,
                enabled=state_name(node.status) == "OPERATION ENABLED",
                timestamp=node.stamp,
            )
        if not self._synced_since_read and self._network is not None:
            self._send_sync()
        self._synced_since_read = False
        return states
