"""A socketcand-protocol TCP server that bridges a python-can bus to clients in other processes.

Python-can's ``virtual`` interface only reaches buses in the same process, and this machine has no
SocketCAN. Serving the bus in socketcand's raw mode lets any process connect with python-can's own
client: ``can.Bus(interface="socketcand", host="127.0.0.1", port=PORT, channel="can0")``.

Protocol (raw mode only): the server greets ``< hi >``; the client sends ``< open can0 >`` and
``< rawmode >``, each answered ``< ok >``; then the client sends ``< send 205 4 1 2 3 4 >`` (id and
bytes in unpadded hex) and receives ``< frame 205 1795238642.596493 01020304 >`` (standard ids as
3 hex digits, extended as 8, data as one hex string). Frames from one client go to the bus and to
the other clients, never back to the sender. Frames for a client are held for a few milliseconds
after its ``< ok >`` to raw mode and then sent in order, because python-can's client reads that
``< ok >`` with a single ``recv`` and would fail if a frame arrived in the same segment.

Two ways to reach the bus: a python-can bus (``bus`` or ``bus_kwargs``; a thread copies the bus's frames to the
clients), or in-process callbacks (``on_frame`` receives each client frame, :meth:`SocketcandServer.publish` sends a
frame to the clients). The emulator uses the second: a frame then crosses no python-can queue, deep copy or extra
thread, which cost most of the emulator's CPU.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import can

log = logging.getLogger(__name__)

#: Delay after the raw-mode ``< ok >`` before frames (held meanwhile) are forwarded to a new client.
RAWMODE_GRACE_S = 0.02
MAX_COMMAND_CHARS = 256
#: Frames the bus answers while one client segment is handled go out together up to this size (python-can's client
#: reads 1024 bytes at a time and warns about a frame cut at that boundary).
BATCH_BYTES = 900


def format_fields(can_id: int, data: bytes, timestamp: float, extended: bool = False) -> bytes:
    """``< frame ID SEC.USEC HEXDATA >`` from the parts of one frame (no message object needed)."""
    text = f"{can_id:08X}" if extended else f"{can_id:03X}"
    return f"< frame {text} {timestamp:.6f} {data.hex().upper()} >".encode("ascii")


def format_frame(msg: can.Message) -> bytes:
    """``< frame ID SEC.USEC HEXDATA >`` for one CAN message."""
    return format_fields(msg.arbitration_id, bytes(msg.data), msg.timestamp or time.time(), msg.is_extended_id)


def parse_send_fields(command: str) -> tuple[int, bool, bytes]:
    """Parse ``< send ID LEN B1 B2 ... >`` into ``(can_id, extended, data)``; ValueError naming what is wrong."""
    parts = command.strip("<> ").split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {command!r}")
    id_text, length = parts[1], int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if length != len(data) or length > 8:
        raise ValueError(f"length {length} does not match {len(data)} data bytes in {command!r}")
    can_id = int(id_text, 16)
    extended = len(id_text) > 3
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"CAN id {id_text} out of range in {command!r}")
    return can_id, extended, data


def parse_send(command: str) -> can.Message:
    """Parse ``< send ID LEN B1 B2 ... >`` into a message; ValueError naming what is wrong."""
    can_id, extended, data = parse_send_fields(command)
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=data, timestamp=time.time())


#: ``on_frame(can_id, data, timestamp)``: a frame a client sent, for the in-process bus.
FrameSink = Callable[[int, bytes, float], None]


class _Client:
    """One connected client: its socket, send lock, raw-mode state and frames held during the grace period."""

    MAX_HELD = 4096

    def __init__(self, sock: socket.socket, peer: Any) -> None:
        self.sock = sock
        self.peer = peer
        self.lock = threading.Lock()
        self.raw = False  # in raw mode: frames are forwarded (held until ``ready``)
        self.ready = False
        self.held: list[bytes] = []
        self.alive = True

    def send(self, payload: bytes) -> bool:
        try:
            with self.lock:
                self.sock.sendall(payload)
            return True
        except OSError:
            self.alive = False
            return False

    def forward(self, frame: bytes) -> bool:
        """Send a frame now, or hold it while the raw-mode ``< ok >`` may still be unread."""
        try:
            with self.lock:
                if not self.ready:
                    if len(self.held) < self.MAX_HELD:
                        self.held.append(frame)
                    return True
                self.sock.sendall(frame)
            return True
        except OSError:
            self.alive = False
            return False

    def release(self) -> None:
        """End of the grace period: flush the held frames in order and forward from now on."""
        try:
            with self.lock:
                if self.held:
                    self.sock.sendall(b"".join(self.held))
                    self.held.clear()
                self.ready = True
        except OSError:
            self.alive = False


class SocketcandServer:
    """Serve ``channel`` of a python-can bus in socketcand raw mode on ``host:port`` (0: any free port).

    Pass an open ``bus`` (not closed by :meth:`stop`), ``bus_kwargs`` for ``can.Bus`` (closed by :meth:`stop`), or
    ``on_frame`` (called on the client's thread with each frame a client sends; frames for the clients go through
    :meth:`publish`). The bus should not receive its own sends (python-can's default).
    """

    def __init__(
        self,
        *,
        bus: can.BusABC | None = None,
        bus_kwargs: Mapping[str, Any] | None = None,
        on_frame: FrameSink | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        channel: str = "can0",
    ) -> None:
        if sum(x is not None for x in (bus, bus_kwargs, on_frame)) != 1:
            raise ValueError("give exactly one of bus, bus_kwargs or on_frame")
        self._on_frame = on_frame
        self._bus_kwargs = dict(bus_kwargs or {})
        self._bus = bus
        self._owns_bus = bus is None
        self.channel = channel
        self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listen.bind((host, port))
        self.host, self.port = self._listen.getsockname()[:2]
        self._clients: list[_Client] = []
        self._clients_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.frames_to_bus = 0
        self.frames_from_bus = 0
        self._batch = threading.local()  # frames published while a client's segment is handled, sent in one write

    @property
    def address(self) -> tuple[str, int]:
        return self.host, self.port

    def start(self) -> SocketcandServer:
        """Open the bus (if needed), listen and start serving on background threads."""
        loops: list[tuple[Callable[[], None], str]] = [(self._accept_loop, "socketcand-accept")]
        if self._on_frame is None:
            if self._bus is None:
                self._bus = can.Bus(**self._bus_kwargs)
            loops.append((self._bus_loop, "socketcand-bus"))
        self._listen.listen(16)
        self._listen.settimeout(0.2)
        for target, name in loops:
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def stop(self) -> None:
        """Disconnect every client, stop the threads and close the bus if this server opened it."""
        self._stop.set()
        with contextlib.suppress(OSError):
            self._listen.close()
        with self._clients_lock:
            clients = list(self._clients)
        for client in clients:
            self._drop(client)
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads.clear()
        if self._owns_bus and self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def __enter__(self) -> SocketcandServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def client_count(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    # ------------------------------------------------------------------ threads
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, peer = self._listen.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(None)
            client = _Client(sock, peer)
            with self._clients_lock:
                self._clients.append(client)
            thread = threading.Thread(target=self._client_loop, args=(client,), name=f"socketcand-{peer}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def _bus_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=0.1)
            except Exception:
                if self._stop.is_set():
                    break
                log.exception("socketcand: bus receive failed")
                time.sleep(0.05)
                continue
            if msg is None or msg.is_error_frame:
                continue
            self.frames_from_bus += 1
            self._broadcast(format_frame(msg), exclude=None)

    def publish(self, can_id: int, data: bytes, timestamp: float | None = None, extended: bool = False) -> None:
        """Send one frame of the in-process bus to every client in raw mode (any thread)."""
        self.frames_from_bus += 1
        payload = format_fields(can_id, data, timestamp or time.time(), extended)
        batch: list[bytes] | None = getattr(self._batch, "frames", None)
        if batch is None:
            self._broadcast(payload, exclude=None)
            return
        batch.append(payload)
        if sum(map(len, batch)) >= BATCH_BYTES:
            self._flush_batch()

    def _flush_batch(self) -> None:
        batch: list[bytes] | None = getattr(self._batch, "frames", None)
        if batch:
            self._broadcast(b"".join(batch), exclude=None)
            batch.clear()

    def _broadcast(self, payload: bytes, exclude: _Client | None) -> None:
        with self._clients_lock:
            clients = [c for c in self._clients if c is not exclude and c.raw]
        for client in clients:
            if not client.forward(payload):
                self._drop(client)

    def _drop(self, client: _Client) -> None:
        client.alive = False
        with self._clients_lock:
            if client in self._clients:
                self._clients.remove(client)
        with contextlib.suppress(OSError):
            client.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            client.sock.close()

    def _client_loop(self, client: _Client) -> None:
        buffer = ""
        stage = "open"
        try:
            client.send(b"< hi >")
            while client.alive and not self._stop.is_set():
                chunk = client.sock.recv(4096)
                if not chunk:
                    break
                buffer += chunk.decode("ascii", errors="replace")
                self._batch.frames = []
                try:
                    buffer, stage = self._handle_buffer(client, buffer, stage)
                finally:
                    self._flush_batch()
                    self._batch.frames = None
                if stage == "closed":
                    return
        except OSError:
            pass
        finally:
            self._drop(client)

    def _handle_buffer(self, client: _Client, buffer: str, stage: str) -> tuple[str, str]:
        """Handle every complete command in ``buffer``; returns what is left of it and the new stage."""
        while True:
            start = buffer.find("<")
            end = buffer.find(">", start + 1)
            if start < 0:
                return "", stage
            if end < 0:
                if len(buffer) - start > MAX_COMMAND_CHARS:
                    log.warning("socketcand %s: discarding over-long command", client.peer)
                    return "", stage
                return buffer[start:], stage
            command, buffer = buffer[start : end + 1], buffer[end + 1 :]
            stage = self._handle(client, command, stage)
            if stage == "closed":
                return "", stage

    def _handle(self, client: _Client, command: str, stage: str) -> str:
        words = command.strip("<> ").split()
        verb = words[0] if words else ""
        if stage == "open":
            if verb == "open" and len(words) == 2 and words[1] == self.channel:
                client.send(b"< ok >")
                return "bcm"
            client.send(b"< error could not open bus >")
            log.warning("socketcand %s: expected '< open %s >', got %r", client.peer, self.channel, command)
            return "closed"
        if stage == "bcm":
            if verb == "rawmode":
                client.send(b"< ok >")
                client.raw = True
                timer = threading.Timer(RAWMODE_GRACE_S, client.release)
                timer.daemon = True
                timer.start()
                return "raw"
            if verb == "echo":
                client.send(b"< echo >")
                return stage
            client.send(b"< error only rawmode is supported >")
            return stage
        # raw mode
        if verb == "send":
            try:
                can_id, extended, data = parse_send_fields(command)
            except ValueError as exc:
                log.warning("socketcand %s: %s", client.peer, exc)
                client.send(b"< error malformed send >")
                return stage
            stamp = time.time()
            self.frames_to_bus += 1
            self._broadcast(format_fields(can_id, data, stamp, extended), exclude=client)
            self._to_bus(can_id, extended, data, stamp)
        elif verb == "echo":
            client.send(b"< echo >")
        return stage

    def _to_bus(self, can_id: int, extended: bool, data: bytes, stamp: float) -> None:
        """Hand a client's frame to the in-process bus or the python-can bus (failures logged, never raised)."""
        if self._on_frame is not None:
            try:
                self._on_frame(can_id, data, stamp)
            except Exception:
                log.exception("socketcand: frame 0x%X could not be delivered", can_id)
            return
        bus = self._bus
        if bus is not None:
            try:
                bus.send(can.Message(arbitration_id=can_id, is_extended_id=extended, data=data, timestamp=stamp))
            except can.CanError as exc:
                log.warning("socketcand: bus send failed: %s", exc)
