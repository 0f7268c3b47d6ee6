"""The emulators' fault-injection control channel (server in each emulator process, client in the daemon and
``likeness sim inject``): msgpack requests over a ZeroMQ REP socket.

An emulator process serves ``ControlServer(endpoint, handler)``; ``handler(request) -> dict`` gets
maps such as ``{"op": "inject", "fault": "stop_heartbeat", "device": 3}`` and returns a reply map.
``likeness sim inject`` is the client. Replies are ``{"ok": true, ...}`` or
``{"ok": false, "error": "..."}``; a handler exception becomes an error reply, never a crash.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from typing import Any

import msgpack
import zmq

log = logging.getLogger(__name__)

#: A control request or reply map.
ControlReply = dict[str, object]
Handler = Callable[[Mapping[str, Any]], Mapping[str, Any]]
MAX_REQUEST_BYTES = 64 * 1024


class ControlServer:
    """Serve fault-injection requests on a background thread until :meth:`close`."""

    def __init__(self, endpoint: str, handler: Handler) -> None:
        self._ctx = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST_BYTES)
        self._sock.bind(endpoint)
        self.endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self._handler = handler
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="sim-control", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        while not self._stop.is_set():
            if not poller.poll(100):
                continue
            raw = self._sock.recv()
            try:
                request = msgpack.unpackb(raw, raw=False)
                if not isinstance(request, dict):
                    raise ValueError("request must be a map")
                reply = {"ok": True, **dict(self._handler(request))}
            except Exception as exc:
                reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            self._sock.send(msgpack.packb(reply, use_bin_type=True))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close(0)


def request(endpoint: str, message: Mapping[str, object], timeout_s: float = 2.0) -> ControlReply:
    """Send one control request and return the reply map; raises TimeoutError if nobody answers."""
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send(msgpack.packb(dict(message), use_bin_type=True))
        if not sock.poll(int(timeout_s * 1000)):
            raise TimeoutError(f"no answer from emulator control endpoint {endpoint} in {timeout_s} s")
        reply = msgpack.unpackb(sock.recv(), raw=False)
    finally:
        sock.close(0)
    if not isinstance(reply, dict):
        raise RuntimeError(f"emulator control endpoint {endpoint} answered {type(reply).__name__}, not a map")
    return reply
