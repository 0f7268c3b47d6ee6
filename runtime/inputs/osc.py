"""The OSC input: python-osc's UDP (and optional TCP) server on threads of the API server process.

Every packet is parsed by python-osc (:class:`~pythonosc.osc_packet.OscPacket`) and its messages resolved through the
address map (:mod:`runtime.inputs.oscmap`). The messages of one bundle that share a timetag become one command, so
they change the head in the same cycle, at their timetag (a tag in the past or "immediately": at once). A message
carries one number, in the channel's unit. A packet with any bad message is refused whole, its reason logged.
Control addresses (enable, disable, play, stop, estop) are served only to senders on the allow-list.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pythonosc import osc_packet
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_server import BlockingOSCUDPServer
from pythonosc.osc_tcp_server import ThreadingOSCTCPServer

from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.inputs.config import OscConfig
from runtime.inputs.oscmap import OscMap
from runtime.inputs.refusals import Refusals
from runtime.rtbudget import RealtimeBudget, as_budget


class _PacketDispatcher(Dispatcher):
    """Hands every packet whole to the input (python-osc's server calls this for each datagram or TCP frame)."""

    def __init__(self, on_packet: Callable[[bytes, tuple[str, int]], None]) -> None:
        super().__init__(strict_timing=False)
        self._on_packet = on_packet

    def call_handlers_for_packet(self, data: bytes, client_address: tuple[str, int]) -> list:
        self._on_packet(data, client_address)
        return []  # nothing is sent back


class _UDPServer(BlockingOSCUDPServer):
    def __init__(self, address: tuple[str, int], dispatcher: Dispatcher, refusals: Refusals) -> None:
        super().__init__(address, dispatcher)
        self.refusals = refusals

    def verify_request(self, request: Any, client_address: Any) -> bool:
        ok = super().verify_request(request, client_address)
        if not ok:
            self.refusals.refuse("not an OSC message or bundle", f"{len(request[0])} bytes from {client_address[0]}")
        return ok


class OscInput:
    """OSC server threads; ``emit`` takes the commands they make."""

    name = "osc"

    def __init__(self, cfg: OscConfig, channels: ChannelMap, emit: Callable[[C.Command], None],
                 estop: Callable[[str], None], priority: int | RealtimeBudget = 0) -> None:
        self.cfg = cfg
        self.priority = as_budget(priority)  # the UDP thread's scheduling (TCP connections keep normal)
        self._udp_thread: int | None = None
        self.map = OscMap(cfg.map, channels, cfg.control_prefix)
        self.emit = emit
        self.trip_estop = estop
        self.refusals = Refusals("osc")
        self.packets = 0
        self.messages = 0
        self._servers: list[Any] = []
        self._threads: list[threading.Thread] = []
        self.bound: dict[str, str] = {}

    def start(self) -> None:
        dispatcher = _PacketDispatcher(self.packet)
        udp = _UDPServer((self.cfg.host, self.cfg.port), dispatcher, self.refusals)
        self._servers.append(udp)
        self.bound["udp"] = _address(udp)
        if self.cfg.tcp is not None:
            tcp = ThreadingOSCTCPServer(self.cfg.tcp, dispatcher)
            tcp.daemon_threads = True
            self._servers.append(tcp)
            self.bound["tcp"] = _address(tcp)
        for i, server in enumerate(self._servers):
            th = threading.Thread(target=self._serve if i == 0 else server.serve_forever, args=(server,) if i == 0
                                  else (), kwargs={"poll_interval": 0.2}, name="likeness-osc", daemon=True)
            th.start()
            self._threads.append(th)

    def _serve(self, server: Any, poll_interval: float) -> None:
        """The UDP server's thread: realtime within its budget (:mod:`runtime.rtbudget`), then serve."""
        self._udp_thread = threading.get_ident()
        self.priority.enter()
        server.serve_forever(poll_interval=poll_interval)

    def close(self) -> None:
        for server in self._servers:
            server.shutdown()
            server.server_close()
        for th in self._threads:
            th.join(timeout=2.0)

    def stats(self) -> dict[str, Any]:
        return {"packets": self.packets, "messages": self.messages, "refused": self.refusals.snapshot(),
                **self.bound}

    # ------------------------------------------------------------------ packets
    def packet(self, data: bytes, client: tuple[str, int]) -> None:
        """One OSC packet (a message or a bundle) from ``client``; the UDP thread's CPU budget is checked after."""
        try:
            self._packet(data, client)
        finally:
            if threading.get_ident() == self._udp_thread:
                self.priority.spent()

    def _packet(self, data: bytes, client: tuple[str, int]) -> None:
        received = time.monotonic()
        self.packets += 1
        try:
            timed = osc_packet.OscPacket(data).messages
        except osc_packet.ParseError as exc:
            self.refusals.refuse("malformed OSC", f"{exc} (from {client[0]})")
            return
        wall = time.time()  # after parsing: the parser stamps "immediately" and past timetags with its own now
        groups: dict[float, list[Any]] = {}
        for tm in timed:
            groups.setdefault(tm.time, []).append(tm.message)
        for when in sorted(groups):
            self._group(groups[when], when, wall, received, client)

    def _group(self, messages: list[Any], when: float, wall: float, received: float, client: tuple[str, int]) -> None:
        indices: list[int] = []
        values: list[float] = []
        for msg in messages:
            self.messages += 1
            address = msg.address
            idx, control = self.map.resolve(address)
            if control is not None:
                self._control(control, msg.params, client, received)
                continue
            if not idx:
                self.refusals.refuse("unmapped address", f"{address} (from {client[0]})")
                return
            params = msg.params
            if len(params) != 1 or isinstance(params[0], bool) or not isinstance(params[0], (int, float)):
                self.refusals.refuse("not one number", f"{address} {params!r} (from {client[0]})")
                return
            value = float(params[0])
            if not math.isfinite(value):
                self.refusals.refuse("non-finite value", f"{address} {value} (from {client[0]})")
                return
            indices.extend(idx)
            values.extend([value] * len(idx))
        if not indices:
            return
        at = None if when <= wall else received + (when - wall)  # the timetag on the daemon clock
        self.emit(C.Live(0, "osc", np.array(indices, dtype=np.intp), np.array(values), at, received,
                         watchdog_s=None if self.cfg.watchdog else math.inf))

    def _control(self, op: str, params: list[Any], client: tuple[str, int], received: float) -> None:
        if client[0] not in self.cfg.control_allow:
            self.refusals.refuse("control address from a sender not on control_allow",
                                 f"{self.cfg.control_prefix}/{op} from {client[0]}")
            return
        if op == "estop":
            reason = (str(params[0]) if params else f"osc from {client[0]}")[:128]
            self.trip_estop(reason)  # reaches the core this cycle, before the command itself
            self.emit(C.EStop(0, reason))
        elif op == "enable":
            self.emit(C.Enable(0))
        elif op == "disable":
            self.emit(C.Disable(0))
        elif op == "stop":
            self.emit(C.StopMotion(0))
        elif op == "play":
            if not params or not isinstance(params[0], str):
                self.refusals.refuse("play needs a clip name", f"{params!r} from {client[0]}")
                return
            loop = len(params) > 1 and bool(params[1])
            self.emit(C.Play(0, params[0], None, 0.0, 1.0, loop, source="osc"))


def _address(server: Any) -> str:
    host, port = server.server_address[:2]
    return f"{host}:{port}"
