"""The sACN (E1.31) input: one universe, received on a thread of the API server process.

Packets are read by :func:`runtime.inputs.e131.parse` (the ``sacn`` library's checks, without its per-slot copy)
from a receiver socket plugged into the library's socket interface, bound exactly where the config says
(loopback unless allowed; ``multicast = true`` joins the universe's group on the bind interface). The library's own
receiver handler keeps one priority and one sequence per universe, not per source, so the merge of several sources is
:class:`runtime.inputs.dmx.Merger` (highest priority, then HTP or LTP). Every packet that changes the merged values
becomes a live command; one that repeats them keeps the input alive (the watchdog) without taking the head over
from another source; a new source takes over. A silent source leaves the merge after ``source_timeout_s`` (E1.31's
network data loss, 2.5 s: a source may repeat unchanged data only once a second); when all are silent that long, the
stream watchdog holds, and eases to neutral as it would for a lost stream (``[safety] watchdog_neutral_s -
watchdog_hold_s`` later).
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from sacn.messages.data_packet import calculate_multicast_addr
from sacn.receiving.receiver_socket_base import ReceiverSocketBase, ReceiverSocketListener

from runtime.core import commands as C
from runtime.core.channels import ChannelMap
from runtime.inputs import e131
from runtime.inputs.config import SacnConfig
from runtime.inputs.dmx import Merger, SlotDecoder
from runtime.inputs.refusals import Refusals, log
from runtime.rtbudget import RealtimeBudget, as_budget


class BoundReceiverSocket(ReceiverSocketBase):
    """A UDP receiver socket for the sacn library, bound to exactly one address (the library's binds every
    interface on Linux)."""

    def __init__(self, listener: ReceiverSocketListener, host: str, port: int, multicast_group: str | None = None,
                 priority: RealtimeBudget | None = None) -> None:
        super().__init__(listener=listener)
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if multicast_group is None:
            self._socket.bind((host, port))
        else:  # a multicast receiver binds the group and joins it on the interface
            self._socket.bind((multicast_group, port))
            self._socket.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                                    socket.inet_aton(multicast_group) + socket.inet_aton(host))
        self._socket.settimeout(0.1)
        self.address = self._socket.getsockname()
        self._run = False
        self._thread: threading.Thread | None = None
        self.priority = priority or RealtimeBudget(0)  # this thread's scheduling (runtime.rtbudget)

    def start(self) -> None:
        self._run = True
        self._thread = threading.Thread(target=self._loop, name="likeness-sacn", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        import select

        self.priority.enter()
        while self._run:
            try:
                data = self._socket.recv(2048)
            except TimeoutError:
                data = None
            except OSError:
                if self._run:
                    log.exception("sACN receive failed")
                return
            try:
                if data is not None:
                    self._listener.on_data(data, time.monotonic())
                # Timeouts are judged only with nothing left to read: a thread that was kept waiting must not find
                # its sources silent while their packets queue in the socket.
                if not select.select([self._socket], [], [], 0)[0]:
                    self._listener.on_periodic_callback(time.monotonic())
            except Exception:  # a bug must not end the input: the packet is lost, the next one is taken
                log.exception("sACN input: handling a packet failed")
            self.priority.spent()

    def stop(self) -> None:
        self._run = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._socket.close()

    def join_multicast(self, multicast_addr: str) -> None:
        raise NotImplementedError("multicast is configured with [inputs.sacn] multicast = true")

    def leave_multicast(self, multicast_addr: str) -> None:
        raise NotImplementedError


class SacnInput(ReceiverSocketListener):
    """Receives one universe from any number of sources, merges and decodes it, and emits live commands."""

    name = "sacn"

    def __init__(self, cfg: SacnConfig, channels: ChannelMap, emit: Callable[[C.Command], None],
                 priority: int | RealtimeBudget = 0) -> None:
        self.cfg = cfg
        self.priority = as_budget(priority)
        self.emit = emit
        self.decoder = SlotDecoder(cfg.slots)
        self.indices = channels.indices(self.decoder.channels)
        self.merger = Merger(cfg.merge, cfg.source_timeout_s)
        self.refusals = Refusals("sacn")
        self.packets = 0
        self.last: np.ndarray | None = None
        self._lock = threading.Lock()
        self._socket: BoundReceiverSocket | None = None
        self.bound: dict[str, Any] = {}

    def start(self) -> None:
        group = calculate_multicast_addr(self.cfg.universe) if self.cfg.multicast else None
        self._socket = BoundReceiverSocket(self, self.cfg.host, self.cfg.port, group, self.priority)
        host, port = self._socket.address[:2]
        self.bound = {"bind": f"{host}:{port}", "universe": self.cfg.universe}
        self._socket.start()

    def close(self) -> None:
        if self._socket is not None:
            self._socket.stop()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            sources = [{"name": s.name, "priority": s.priority} for s in self.merger.sources.values()]
        return {"packets": self.packets, "sources": sources, "merge": self.cfg.merge,
                "refused": self.refusals.snapshot(), **self.bound}

    # ------------------------------------------------------------------ the library's listener interface
    def on_data(self, data: bytes, current_time: float) -> None:
        self.packets += 1
        try:
            packet = e131.parse(data)
        except (TypeError, ValueError) as exc:
            self.refusals.refuse("not an sACN data packet", str(exc)[:120])
            return
        if packet.universe != self.cfg.universe:
            self.refusals.refuse("another universe", f"{packet.universe} (configured: {self.cfg.universe})")
            return
        if packet.dmxStartCode != 0:
            self.refusals.refuse("not DMX level data", f"start code 0x{packet.dmxStartCode:02X}")
            return
        cid = bytes(packet.cid)
        with self._lock:
            if packet.option_StreamTerminated:
                self.merger.terminate(cid)
                log.info("sACN source %r stopped its stream", packet.sourceName)
                self._send(current_time, takeover=False)
                return
            if packet.option_PreviewData:
                self.refusals.refuse("preview data", packet.sourceName)
                return
            ok, new = self.merger.update(cid, packet.priority, packet.dmxData, current_time, packet.sourceName,
                                         packet.sequence)
            if not ok:
                self.refusals.refuse("out of sequence", f"{packet.sourceName} sequence {packet.sequence}")
                return
            if new:
                log.info("sACN source %r (priority %d) on universe %d", packet.sourceName, packet.priority,
                         packet.universe)
            self._send(current_time, takeover=new)

    def on_periodic_callback(self, current_time: float) -> None:
        with self._lock:
            gone = self.merger.expire(current_time)
            if gone:
                log.warning("sACN source %s silent for %g s: left the merge", ", ".join(map(repr, gone)),
                            self.cfg.source_timeout_s)
                if self.merger.sources:  # the merge falls back to the sources left; no new activity: no takeover
                    self._send(current_time, takeover=False, follow=False)

    def _send(self, received: float, takeover: bool, follow: bool = True) -> None:
        """Emit the merged values; they take the head over when a source is new (``takeover``) or, with ``follow``,
        when they changed."""
        merged = self.merger.merged()
        if merged is None:
            self.last = None
            return
        values = self.decoder.decode(merged)
        changed = self.last is None or not np.array_equal(values, self.last)
        self.last = values
        self.emit(C.Live(0, "sacn", self.indices, values, None, received, takeover=takeover or (follow and changed),
                         watchdog_s=self.cfg.source_timeout_s))
