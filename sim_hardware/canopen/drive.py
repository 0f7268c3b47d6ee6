"""One emulated CiA 402 servo drive: a canopen ``LocalNode`` plus the profile's behaviour.

canopen's ``LocalNode`` gives the SDO server, NMT slave and EMCY producer; this module adds what a
real drive does on top: the CiA 402 power state machine driven by the controlword, SYNC-driven
RPDO/TPDO exchange wired to the drive's live data (``LocalNode`` leaves PDOs unconnected), a
heartbeat producer clocked by the drive set's physics thread (so it can be stopped and resumed),
cyclic synchronous position (mode 8) and profile position (mode 1) on a simulated motor, a
following-error monitor that faults with EMCY 0x8611, and fault injection hooks.

Threads: SDO, NMT, SYNC and RPDO handlers run on the bus notifier thread, :meth:`EmulatedDrive.step`
and :meth:`EmulatedDrive.step_comm` on the physics thread; one re-entrant lock per drive guards
the state, and every handler is short.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from canopen import LocalNode
from canopen.nmt import NmtSlave
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from sim_hardware.canopen import motor
from sim_hardware.canopen.od import MODE_CSP, MODE_PROFILE_POSITION, PDO_DISABLED, build_od

if TYPE_CHECKING:
    import canopen

log = logging.getLogger(__name__)

# CiA 402 power states.
NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

_STATUS_BITS = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0021,
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP_ACTIVE: 0x0017,
    FAULT_REACTION_ACTIVE: 0x001F,
    FAULT: 0x0008,
}
_TORQUE_STATES = (OPERATION_ENABLED, QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE)

SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800
SW_OP_MODE_12 = 0x1000  # CSP: drive follows the command value; PP: set-point acknowledge
SW_OP_MODE_13 = 0x2000  # following error

EMCY_FOLLOWING_ERROR = 0x8611
EMCY_PDO_LENGTH = 0x8210
EMCY_GENERIC = 0x1000

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127

_PDO_RANGES = ((0x1400, 0x1403), (0x1600, 0x1603), (0x1800, 0x1803), (0x1A00, 0x1A03))
_PDO_INDICES = frozenset(i for lo, hi in _PDO_RANGES for i in range(lo, hi + 1))


def error_register_for(code: int) -> int:
    """CiA 301 error register (0x1001) bits for an EMCY error code."""
    reg = 0x01
    if code >> 12 == 0x2:
        reg |= 0x02
    elif code >> 12 == 0x3:
        reg |= 0x04
    elif code >> 12 == 0x4:
        reg |= 0x08
    elif code >> 8 == 0x81 or code >> 8 == 0x82:
        reg |= 0x10
    elif code >> 12 == 0x8 or code >> 12 == 0x6:
        reg |= 0x20
    elif code >> 8 == 0xFF:
        reg |= 0x80
    return reg


@dataclass(slots=True)
class _Pdo:
    """Decoded communication + mapping parameters of one PDO."""

    number: int
    cob_id: int
    valid: bool
    trans_type: int
    event_ms: int
    entries: list[tuple[int, int, int]] = field(default_factory=list)  # (index, subindex, bytes)
    #: per entry (index, subindex, its object-dictionary variable): a TPDO's values read without the lookups
    readers: list[tuple[int, int, Any]] = field(default_factory=list)
    length: int = 0
    last_payload: bytes | None = None
    next_event: float = 0.0
    next_check: float = 0.0


class DriveNmt(NmtSlave):
    """NMT slave whose heartbeat is produced by the drive's clock, and whose resets reboot the drive."""

    def __init__(self, node_id: int, local_node: LocalNode, drive: EmulatedDrive) -> None:
        super().__init__(node_id, local_node)
        self._drive = drive

    def on_command(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) < 2:
            return
        cmd, node_id = struct.unpack_from("BB", data)
        if node_id not in (self.id, 0):
            return
        if cmd in (0x81, 0x82):  # reset node / reset communication
            self._drive.reset(application=cmd == 0x81)
            return
        old = self._state
        super().on_command(can_id, data, timestamp)
        if self._state != old:
            self._drive._on_nmt_state(self._state)

    def start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self._heartbeat_time_ms = int(heartbeat_time_ms)

    def stop_heartbeat(self) -> None:
        self._heartbeat_time_ms = 0

    def update_heartbeat(self) -> None:
        """The producer reads the state at every beat; nothing to update."""

    @property
    def heartbeat_time_ms(self) -> int:
        return self._heartbeat_time_ms


class _DriveNode(LocalNode):
    """``LocalNode`` with the drive's NMT slave in place of the stock one."""

    def __init__(self, node_id: int, od: canopen.ObjectDictionary, drive: EmulatedDrive) -> None:
        super().__init__(node_id, od)
        self._write_callbacks.remove(self.nmt.on_write)
        self.nmt = DriveNmt(node_id, self, drive)
        self.add_write_callback(self.nmt.on_write)


class EmulatedDrive:
    """A CiA 402 drive with node id ``node_id``; attach it to a canopen ``Network`` and boot it.

    Ground truth for tests and mechanisms: :attr:`position_counts`, :attr:`velocity_counts`,
    :attr:`current_amps`, :attr:`state` (CiA 402 state name), :attr:`nmt_state`.
    Asynchronous TPDOs (transmission type 254/255) go out on their event timer, at once when the
    statusword changes, and when any mapped value changed at the next check (every 5 ms).
    """

    ASYNC_CHECK_PERIOD = 0.005
    VELOCITY_FILTER_S = 0.01

    def __init__(
        self,
        node_id: int,
        *,
        params: motor.MotorParams | None = None,
        initial_position_counts: float = 0.0,
        heartbeat_ms: int = 0,
        following_error_window: int = 5000,
    ) -> None:
        self.node_id = node_id
        self.params = params or motor.MotorParams()
        self._od_options = {"heartbeat_ms": heartbeat_ms, "following_error_window": following_error_window}
        self.od = build_od(node_id, **self._od_options)
        self.node = _DriveNode(node_id, self.od, self)
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self._lock = threading.RLock()
        self._motor = motor.MotorState(position=float(initial_position_counts))
        self._velocity_filtered = 0.0
        self._network: canopen.Network | None = None
        self.heartbeat_enabled = True
        self.feedback_frozen = False  # fault injection: SYNCs ignored, so no TPDOs (the drive stops reporting)
        self._stuck_at: float | None = None  # fault injection: the reported position stays here (slipping output)
        self._next_heartbeat = 0.0
        self.emcy_log: list[int] = []
        self._reset_profile_state()
        self._params_from_od()

    # ------------------------------------------------------------------ ground truth
    @property
    def position_counts(self) -> float:
        return self._motor.position

    @property
    def velocity_counts(self) -> float:
        return self._motor.velocity

    @property
    def current_amps(self) -> float:
        return self._motor.current

    @property
    def state(self) -> str:
        return self._state

    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state

    @property
    def statusword(self) -> int:
        return self._statusword()

    @property
    def jammed(self) -> bool:
        return self._motor.jammed

    @property
    def slipping(self) -> bool:
        """Whether the reported position is stuck (:meth:`set_slipping`)."""
        return self._stuck_at is not None

    # ------------------------------------------------------------------ life cycle
    def _reset_profile_state(self) -> None:
        self._state = NOT_READY
        self._controlword = 0
        self._mode = 0
        self._demand = self._motor.position
        self._demand_velocity = 0.0
        self._target = round(self._motor.position)
        self._seg_start = self._demand
        self._seg_end = self._demand
        self._seg_t = 0.0
        self._seg_T = 0.0
        self._pp_target: float | None = None
        self._pp_ack = False
        self._last_target_time = 0.0
        self._period_estimate = 0.01
        self._fe_time = 0.0
        self._error_code = 0
        self._error_register = 0
        self._internal_limit = False
        self._pending_rpdos: dict[int, tuple[_Pdo, bytes]] = {}
        self._rpdos: dict[int, _Pdo] = {}
        self._tpdos: list[_Pdo] = []
        self._subscribed: list[int] = []
        self._pdo_dirty = True
        self._sync_count = 0
        self._last_status_sent = -1

    def _params_from_od(self) -> None:
        """Cache the parameters the physics step reads (from the data store or OD defaults)."""
        g = self._get
        self._fe_window = g(0x6065)
        self._fe_timeout = g(0x6066) / 1000.0
        self._pos_window = g(0x6067)
        self._max_velocity = float(g(0x607F))
        self._profile_velocity = float(g(0x6081))
        self._profile_accel = float(max(g(0x6083), 1))
        self._profile_decel = float(max(g(0x6084), 1))
        self._quick_stop_decel = float(max(g(0x6085), 1))
        self._quick_stop_option = g(0x605A)
        self._fault_reaction_option = g(0x605E)
        self._limit_min = g(0x607D, 1)
        self._limit_max = g(0x607D, 2)
        value, index = g(0x60C2, 1), g(0x60C2, 2)
        self._interp_period = value * 10.0**index
        rated = g(0x6075) / 1000.0
        self._rated_current = rated
        self._max_current = rated * g(0x6073) / 1000.0
        self._rated_torque = g(0x6076) / 1000.0

    def _get(self, index: int, subindex: int = 0) -> Any:
        obj = self.od[index]
        if subindex or not hasattr(obj, "decode_raw"):
            obj = obj[subindex]
        return obj.decode_raw(self.node.get_data(index, subindex))

    def attach(self, network: canopen.Network) -> None:
        """Join ``network`` (SDO server, NMT, SYNC and PDO subscriptions)."""
        self._network = network
        network.add_node(self.node)
        network.subscribe(0x80, self._on_sync)

    def detach(self) -> None:
        """Leave the network (used when the drive set stops)."""
        if self._network is None:
            return
        net = self._network
        for cob in self._subscribed:
            net.unsubscribe(cob, self._on_rpdo)
        self._subscribed = []
        net.unsubscribe(0x80, self._on_sync)
        del net[self.node_id]
        self._network = None

    def boot(self) -> None:
        """Power-on: send the boot-up message, enter pre-operational and SWITCH ON DISABLED."""
        with self._lock:
            nmt = self.node.nmt
            nmt._state = NMT_INITIALISING
            self._send(0x700 + self.node_id, b"\x00")
            nmt._state = NMT_PRE_OPERATIONAL
            nmt.start_heartbeat(self._get(0x1017))
            self._next_heartbeat = 0.0
            self._state = SWITCH_ON_DISABLED  # transition 1 is automatic
            self._reload_pdos()

    def reset(self, application: bool = True) -> None:
        """NMT reset node (``application``) or reset communication: restore defaults and boot again."""
        with self._lock:
            if application:
                self.node.data_store.clear()
                self._reset_profile_state()
            else:
                for index in [i for i in self.node.data_store if 0x1000 <= i <= 0x1FFF]:
                    del self.node.data_store[index]
                self._pdo_dirty = True
            self._params_from_od()
            self.boot()

    # ------------------------------------------------------------------ sending
    def _send(self, can_id: int, data: bytes) -> None:
        if self._network is not None:
            self._network.send_message(can_id, data)

    def _emcy(self, code: int, register: int) -> None:
        self.emcy_log.append(code)
        self._send(0x80 + self.node_id, struct.pack("<HB5s", code, register, b""))

    # ------------------------------------------------------------------ OD callbacks
    def _on_read(self, index: int, subindex: int, od: Any) -> Any:
        if index == 0x6041:
            return self._statusword()
        if index == 0x6064:
            return _clamp_i32(round(self._motor.position if self._stuck_at is None else self._stuck_at))
        if index == 0x606C:
            return _clamp_i32(round(self._velocity_filtered))
        if index == 0x6062:
            return _clamp_i32(round(self._demand))
        if index == 0x60F4:
            return _clamp_i32(round(self._demand - self._motor.position))
        if index == 0x6078:
            return _clamp_i16(round(1000.0 * self._motor.current / self._rated_current))
        if index == 0x6077:
            torque = self._motor.current * self.params.torque_constant
            return _clamp_i16(round(1000.0 * torque / self._rated_torque))
        if index == 0x6061:
            return self._mode
        if index == 0x603F:
            return self._error_code
        if index == 0x1001:
            return self._error_register
        return None

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index in _PDO_INDICES:
            self._check_pdo_write(index, subindex, data)
            self._pdo_dirty = True
            return
        value = od.decode_raw(data)
        with self._lock:
            if index == 0x6040:
                self._apply_controlword(value)
            elif index == 0x6060:
                if value not in (0, MODE_PROFILE_POSITION, MODE_CSP):
                    raise SdoAbortedError(0x06090030)
                if value != self._mode:
                    self._mode = value
                    self._hold_here()
            elif index == 0x607A:
                self._new_target(value)
            elif index in (0x6065, 0x6066, 0x6067, 0x6073, 0x6075, 0x6076, 0x607D, 0x607F, 0x6081, 0x6083, 0x6084,
                           0x6085, 0x605A, 0x605E, 0x60C2):
                # Store first so the cache sees the new value; LocalNode stores it again afterwards.
                self.node.data_store.setdefault(index, {})[subindex] = bytes(data)
                self._params_from_od()

    def _check_pdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """Refuse mappings a real drive refuses: unknown, unmappable or oversize objects."""
        if not (0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03):
            return
        (value,) = struct.unpack_from("<I", data.ljust(4, b"\x00")) if subindex else (data[0],)
        if subindex == 0:
            total = 0
            for sub in range(1, value + 1):
                entry = struct.unpack("<I", self.node.get_data(index, sub))[0]
                total += entry & 0xFF
            if value > 8 or total > 64:
                raise SdoAbortedError(0x06040042)
            return
        if value == 0:
            return
        obj_index, obj_sub, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        try:
            obj = self.od[obj_index]
            if not hasattr(obj, "decode_raw"):
                obj = obj[obj_sub]
        except KeyError:
            raise SdoAbortedError(0x06020000) from None
        if not obj.pdo_mappable or len(obj) != bits:
            raise SdoAbortedError(0x06040041)

    # ------------------------------------------------------------------ CiA 402 state machine
    def _statusword(self) -> int:
        sw = _STATUS_BITS[self._state] | SW_REMOTE
        if self._internal_limit:
            sw |= SW_INTERNAL_LIMIT
        if self._error_register and self._state not in (FAULT, FAULT_REACTION_ACTIVE):
            sw |= 0x0080  # warning
        if self._state == OPERATION_ENABLED:
            if self._mode == MODE_CSP:
                sw |= SW_OP_MODE_12
                if abs(self._target - self._motor.position) <= self._pos_window:
                    sw |= SW_TARGET_REACHED
            elif self._mode == MODE_PROFILE_POSITION:
                if self._pp_ack:
                    sw |= SW_OP_MODE_12
                if (self._pp_target is None or self._demand == self._pp_target) and abs(
                    self._demand - self._motor.position
                ) <= self._pos_window:
                    sw |= SW_TARGET_REACHED
            if abs(self._demand - self._motor.position) > self._fe_window:
                sw |= SW_OP_MODE_13
        elif self._state == QUICK_STOP_ACTIVE and self._demand_velocity == 0.0:
            sw |= SW_TARGET_REACHED
        return sw

    def _apply_controlword(self, cw: int) -> None:
        prev, self._controlword = self._controlword, cw
        state = self._state
        if state == FAULT:
            if cw & 0x80 and not prev & 0x80:
                self._fault_reset()
            return
        if state in (FAULT_REACTION_ACTIVE, NOT_READY):
            return
        if not cw & 0x02:  # disable voltage
            self._set_state(SWITCH_ON_DISABLED)
        elif not cw & 0x04:  # quick stop
            if state == OPERATION_ENABLED:
                self._start_ramp(QUICK_STOP_ACTIVE)
            elif state in (READY_TO_SWITCH_ON, SWITCHED_ON):
                self._set_state(SWITCH_ON_DISABLED)
        elif not cw & 0x01:  # shutdown
            if state in (SWITCH_ON_DISABLED, SWITCHED_ON, OPERATION_ENABLED):
                self._set_state(READY_TO_SWITCH_ON)
        elif not cw & 0x08:  # switch on / disable operation
            if state in (READY_TO_SWITCH_ON, OPERATION_ENABLED):
                self._set_state(SWITCHED_ON)
        else:  # enable operation
            resume = state == QUICK_STOP_ACTIVE and self._quick_stop_option in (5, 6, 7, 8)
            if state in (READY_TO_SWITCH_ON, SWITCHED_ON) or resume:
                self._set_state(OPERATION_ENABLED)
        if self._state == OPERATION_ENABLED and self._mode == MODE_PROFILE_POSITION:
            self._profile_controlword(prev, cw)

    def _set_state(self, new: str) -> None:
        if new == self._state:
            return
        old, self._state = self._state, new
        log.debug("drive %d: %s -> %s", self.node_id, old, new)
        if new == OPERATION_ENABLED:
            self._hold_here()
        elif new not in _TORQUE_STATES:
            self._demand = self._motor.position
            self._demand_velocity = 0.0

    def _hold_here(self) -> None:
        """Hold the actual position: demand and target become the present position."""
        pos = self._motor.position
        self._demand = pos
        self._demand_velocity = 0.0
        self._seg_start = self._seg_end = pos
        self._seg_t = self._seg_T = 0.0
        self._pp_target = None
        self._pp_ack = False
        self._fe_time = 0.0
        self._target = round(pos)
        self.node.data_store.setdefault(0x607A, {})[0] = struct.pack("<i", _clamp_i32(self._target))

    def _start_ramp(self, state: str) -> None:
        self._demand_velocity = self._motor.velocity
        self._demand = self._motor.position
        self._state = state

    def _clamp_target(self, target: float) -> float:
        self._internal_limit = False
        if self._limit_min < self._limit_max:
            if target < self._limit_min:
                self._internal_limit = True
                return float(self._limit_min)
            if target > self._limit_max:
                self._internal_limit = True
                return float(self._limit_max)
        return float(target)

    def _new_target(self, value: int) -> None:
        self._target = value
        if self._state != OPERATION_ENABLED or self._mode != MODE_CSP:
            return
        # Interpolate over the measured target period (as drives that lock onto SYNC do), seeded with
        # 0x60C2; a pause longer than 0.1 s restarts from 0x60C2.
        now = time.monotonic()
        gap = now - self._last_target_time
        self._last_target_time = now
        if 0.0005 <= gap <= 0.1:
            self._period_estimate = 0.7 * self._period_estimate + 0.3 * gap
        else:
            self._period_estimate = self._interp_period
        self._seg_start = self._demand
        self._seg_end = self._clamp_target(value)
        self._seg_t = 0.0
        self._seg_T = self._period_estimate

    def _profile_controlword(self, prev: int, cw: int) -> None:
        if cw & 0x10 and not prev & 0x10:  # new set-point
            target = float(self._target)
            if cw & 0x40:  # relative
                base = self._pp_target if self._pp_target is not None else self._demand
                target += base
            self._pp_target = self._clamp_target(target)
            self._pp_ack = True
        elif not cw & 0x10:
            self._pp_ack = False

    def raise_fault(self, code: int = EMCY_GENERIC) -> None:
        """Enter FAULT REACTION ACTIVE (torque on) or FAULT and send EMCY ``code``."""
        with self._lock:
            if self._state in (FAULT, FAULT_REACTION_ACTIVE):
                return
            self._error_code = code & 0xFFFF
            self._error_register |= error_register_for(code)
            self._emcy(self._error_code, self._error_register)
            if self._state in _TORQUE_STATES and self._fault_reaction_option != 0:
                self._start_ramp(FAULT_REACTION_ACTIVE)
            else:
                self._state = FAULT
                self._demand = self._motor.position
                self._demand_velocity = 0.0
            log.info("drive %d: fault 0x%04X", self.node_id, code)

    def _fault_reset(self) -> None:
        self._error_code = 0
        self._error_register = 0
        self._fe_time = 0.0
        self._state = SWITCH_ON_DISABLED
        self._emcy(0, 0)

    # ------------------------------------------------------------------ fault injection
    def set_jammed(self, jammed: bool, offset_counts: float = 0.0) -> None:
        """Block the rotor (an obstacle); ``offset_counts`` also displaces it, like a crash."""
        with self._lock:
            self._motor.jammed = jammed
            self._motor.position += offset_counts
            if jammed:
                self._motor.velocity = 0.0

    def set_slipping(self, slipping: bool) -> None:
        """A slipping output stage (a load-side encoder behind a slipping coupling): the reported position actual
        (0x6064) stays where it is while the motor keeps following its demand, so the drive itself sees no following
        error; only the master can tell."""
        with self._lock:
            self._stuck_at = self._motor.position if slipping else None

    # ------------------------------------------------------------------ PDOs
    def _reload_pdos(self) -> None:
        """Decode the PDO records and (re)subscribe the RPDO COB-IDs."""
        rpdos: dict[int, _Pdo] = {}
        tpdos: list[_Pdo] = []
        for n in range(4):
            for base, target in ((0x1400, None), (0x1800, tpdos)):
                cob = self._get(base + n, 1)
                pdo = _Pdo(
                    number=n + 1,
                    cob_id=cob & 0x7FF,
                    valid=not cob & PDO_DISABLED,
                    trans_type=self._get(base + n, 2),
                    event_ms=self._get(base + n, 5) if base == 0x1800 else 0,
                )
                for sub in range(1, self._get(base + 0x200 + n, 0) + 1):
                    entry = self._get(base + 0x200 + n, sub)
                    if entry:
                        pdo.entries.append((entry >> 16, (entry >> 8) & 0xFF, (entry & 0xFF) // 8))
                pdo.length = sum(e[2] for e in pdo.entries)
                if target is not None:
                    pdo.readers = [(i, s, self._od_variable(i, s)) for i, s, _ in pdo.entries]
                if target is None:
                    if pdo.valid and pdo.entries:
                        rpdos[pdo.cob_id] = pdo
                else:
                    target.append(pdo)
        net = self._network
        if net is not None:
            for cob in self._subscribed:
                net.unsubscribe(cob, self._on_rpdo)
            for cob in rpdos:
                net.subscribe(cob, self._on_rpdo)
        self._subscribed = list(rpdos)
        self._rpdos, self._tpdos = rpdos, tpdos
        self._pending_rpdos = {}
        self._pdo_dirty = False

    def _on_nmt_state(self, state: int) -> None:
        with self._lock:
            if state == NMT_OPERATIONAL:
                self._reload_pdos()
                self._sync_count = 0
                self._last_status_sent = -1

    def _tpdo_payload(self, pdo: _Pdo) -> bytes:
        """The TPDO's mapped values, as ``LocalNode.get_data`` gives them: this drive's read callback (its only one)
        encoded by the entry's variable, else the stored value; the variables looked up once per PDO layout."""
        parts = []
        for index, subindex, var in pdo.readers:
            value = None if var is None else self._on_read(index, subindex, var)
            parts.append(self.node.get_data(index, subindex) if value is None else var.encode_raw(value))
        return b"".join(parts)

    def _od_variable(self, index: int, subindex: int) -> Any:
        """The object-dictionary variable at ``index``:``subindex`` (None where there is none: read as before)."""
        try:
            obj = self.od[index]
            return obj if isinstance(obj, ODVariable) else obj[subindex]
        except KeyError:
            return None

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.node.nmt._state != NMT_OPERATIONAL or self.feedback_frozen:
            return
        with self._lock:
            if self._pdo_dirty:
                self._reload_pdos()
            pending, self._pending_rpdos = self._pending_rpdos, {}
            for pdo, payload in pending.values():
                self._apply_rpdo(pdo, payload)
            self._sync_count += 1
            frames = []
            for pdo in self._tpdos:
                if not pdo.valid or not pdo.entries:
                    continue
                if 1 <= pdo.trans_type <= 240:
                    if self._sync_count % pdo.trans_type == 0:
                        frames.append((pdo.cob_id, self._tpdo_payload(pdo)))
                elif pdo.trans_type == 0:
                    payload = self._tpdo_payload(pdo)
                    if payload != pdo.last_payload:
                        pdo.last_payload = payload
                        frames.append((pdo.cob_id, payload))
        for cob, payload in frames:
            self._send(cob, payload)

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.node.nmt._state != NMT_OPERATIONAL:
            return
        with self._lock:
            pdo = self._rpdos.get(can_id)
            if pdo is None:
                return
            if len(data) < pdo.length:
                self._emcy(EMCY_PDO_LENGTH, self._error_register | 0x10)
                return
            if pdo.trans_type <= 240:
                self._pending_rpdos[can_id] = (pdo, bytes(data))
            else:
                self._apply_rpdo(pdo, bytes(data))

    def _apply_rpdo(self, pdo: _Pdo, payload: bytes) -> None:
        offset = 0
        for index, subindex, size in pdo.entries:
            try:
                self.node.set_data(index, subindex, payload[offset : offset + size])
            except SdoAbortedError as exc:
                log.debug("drive %d: RPDO%d write 0x%04X refused: %s", self.node_id, pdo.number, index, exc)
            offset += size

    # ------------------------------------------------------------------ time
    def step(self, dt: float, substeps: int = 1) -> None:
        """Advance the motion and the motor model by ``substeps`` steps of ``dt`` seconds."""
        with self._lock:
            for _ in range(substeps):
                self._step_once(dt)

    def _step_once(self, dt: float) -> None:
        state = self._state
        m = self._motor
        p = self.params
        # 0x606C reports the velocity through a first-order filter, as drives do.
        self._velocity_filtered += (m.velocity - self._velocity_filtered) * min(1.0, dt / self.VELOCITY_FILTER_S)
        if state == OPERATION_ENABLED:
            if self._mode == MODE_CSP:
                if self._seg_t < self._seg_T:
                    self._seg_t += dt
                    frac = min(1.0, self._seg_t / self._seg_T)
                    self._demand = self._seg_start + (self._seg_end - self._seg_start) * frac
                    self._demand_velocity = (self._seg_end - self._seg_start) / self._seg_T if frac < 1.0 else 0.0
                else:
                    self._demand = self._seg_end
                    self._demand_velocity = 0.0
            elif self._mode == MODE_PROFILE_POSITION and self._pp_target is not None:
                halt = bool(self._controlword & 0x100)
                self._profile_step(dt, self._demand if halt else self._pp_target, halt)
            else:
                self._demand_velocity = 0.0
            motor.step_closed_loop(p, m, self._demand, self._demand_velocity, dt, self._max_velocity,
                                   self._max_current)
            self._check_following_error(dt)
        elif state in (QUICK_STOP_ACTIVE, FAULT_REACTION_ACTIVE):
            decel = self._quick_stop_decel
            option = self._quick_stop_option if state == QUICK_STOP_ACTIVE else self._fault_reaction_option
            if option in (1, 5):
                decel = self._profile_decel
            v = self._demand_velocity
            dv = decel * dt
            v = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
            demand = self._demand + v * dt
            if self._limit_min < self._limit_max and not self._limit_min <= demand <= self._limit_max:
                demand = min(max(demand, self._limit_min), self._limit_max)  # the ramp ends at a software limit
                v = 0.0
            self._demand_velocity = v
            self._demand = demand
            motor.step_closed_loop(p, m, self._demand, v, dt, self._max_velocity, self._max_current)
            if v == 0.0:
                if state == FAULT_REACTION_ACTIVE:
                    self._state = FAULT
                elif option in (0, 1, 2, 3, 4):
                    self._set_state(SWITCH_ON_DISABLED)
        else:
            motor.step_coast(p, m, dt)
            self._demand = m.position

    def _profile_step(self, dt: float, target: float, halt: bool) -> None:
        distance = target - self._demand
        v = self._demand_velocity
        v_max = min(self._profile_velocity, self._max_velocity)
        v_brake = math.sqrt(2.0 * self._profile_decel * abs(distance))
        v_goal = math.copysign(min(v_max, v_brake), distance) if distance else 0.0
        rate = (self._profile_accel if abs(v_goal) > abs(v) and v_goal * v >= 0 else self._profile_decel) * dt
        v = v_goal if abs(v_goal - v) <= rate else v + math.copysign(rate, v_goal - v)
        step = v * dt
        if not halt and (abs(step) >= abs(distance) or (abs(distance) < 0.5 and abs(v) < rate)):
            self._demand = target
            self._demand_velocity = 0.0
        else:
            self._demand += step
            self._demand_velocity = v

    def _check_following_error(self, dt: float) -> None:
        if abs(self._demand - self._motor.position) > self._fe_window:
            self._fe_time += dt
            if self._fe_time >= self._fe_timeout:
                self.raise_fault(EMCY_FOLLOWING_ERROR)
        else:
            self._fe_time = 0.0

    def step_comm(self, now: float) -> None:
        """Time-driven communication (physics thread): heartbeat and event-timer/on-change TPDOs."""
        nmt = self.node.nmt
        frames = []
        with self._lock:
            period = nmt.heartbeat_time_ms / 1000.0
            if period > 0 and self.heartbeat_enabled and nmt._state != NMT_INITIALISING and now >= self._next_heartbeat:
                frames.append((0x700 + self.node_id, bytes([nmt._state])))
                late = now - self._next_heartbeat
                self._next_heartbeat = now + period if late > period else self._next_heartbeat + period
            if nmt._state == NMT_OPERATIONAL and not self._pdo_dirty:
                status = self._statusword()
                for pdo in self._tpdos:
                    if not pdo.valid or pdo.trans_type < 254 or not pdo.entries:
                        continue
                    status_changed = status != self._last_status_sent and any(i == 0x6041 for i, _, _ in pdo.entries)
                    timer_due = pdo.event_ms > 0 and now >= pdo.next_event
                    if not (status_changed or timer_due or now >= pdo.next_check):
                        continue
                    payload = self._tpdo_payload(pdo)
                    pdo.next_check = now + self.ASYNC_CHECK_PERIOD
                    if status_changed or timer_due or payload != pdo.last_payload:
                        pdo.last_payload = payload
                        pdo.next_event = now + pdo.event_ms / 1000.0
                        frames.append((pdo.cob_id, payload))
                self._last_status_sent = status
        for cob, payload in frames:
            self._send(cob, payload)


def _clamp_i32(value: int) -> int:
    return max(-(2**31), min(2**31 - 1, value))


def _clamp_i16(value: int) -> int:
    return max(-(2**15), min(2**15 - 1, value))
