"""The daemon's protocol client (DEALER for commands, SUB for telemetry), shared by every client: the CLI, the
studio, calibration and tests.

It speaks only what ``docs/protocol.md`` documents: msgpack maps with ``op`` and ``id``; optional CURVE keys.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import msgpack
import zmq


class DaemonError(Exception):
    """The daemon answered ``ok: false``; ``code`` is the protocol error code, ``error`` the typed error it stands
    for (:mod:`models.errors`)."""

    def __init__(self, op: str, code: str, message: str) -> None:
        from models.protocol import error_for

        super().__init__(f"{op}: {code}: {message}")
        self.op = op
        self.code = code
        self.message = message
        self.error = error_for(code, f"{op}: {message}")


class DaemonTimeout(TimeoutError):
    """No reply within the timeout (daemon not running, wrong endpoint, or key not allowed)."""


def _curve_setup(sock: zmq.Socket, client_key: str | Path | None, server_key: str | Path | None) -> None:
    if client_key is None and server_key is None:
        return
    from zmq.auth import load_certificate

    if client_key is None or server_key is None:
        raise ValueError("CURVE needs both the client secret key file and the server public key file")
    public, secret = load_certificate(str(client_key))
    server_public, _ = load_certificate(str(server_key))
    if secret is None:
        raise ValueError(f"{client_key}: holds no secret key")
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_serverkey = server_public


class Client:
    """Request/reply over a DEALER socket; :meth:`call` raises :class:`DaemonError` on error replies."""

    def __init__(self, endpoint: str = "tcp://127.0.0.1:5555", timeout: float = 5.0,
                 client_key: str | Path | None = None, server_key: str | Path | None = None) -> None:
        self.endpoint = endpoint
        self.timeout = timeout
        self._ctx = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.DEALER)
        self._sock.setsockopt(zmq.LINGER, 0)
        _curve_setup(self._sock, client_key, server_key)
        self._sock.connect(endpoint)
        self._ids = itertools.count(1)

    def close(self) -> None:
        self._sock.close(0)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def send_raw(self, payload: bytes, timeout: float | None = None) -> Any:
        """Send raw bytes as a request and return the decoded reply (for tests of malformed input)."""
        self._send(payload, timeout)
        return self._recv(timeout)

    def _send(self, payload: bytes, timeout: float | None) -> None:
        """Send within the timeout: a DEALER with no connected peer (daemon down, or its handshake refused, as for
        a key it does not allow) would otherwise block the caller for good."""
        wait = self.timeout if timeout is None else timeout
        if not self._sock.poll(int(1000 * wait), zmq.POLLOUT):
            raise DaemonTimeout(f"could not send to {self.endpoint} within {wait} s (daemon not running, wrong "
                                "endpoint, or key not allowed)")
        try:
            self._sock.send(payload, zmq.NOBLOCK)
        except zmq.Again:
            raise DaemonTimeout(f"could not send to {self.endpoint} (no connected peer)") from None

    def _recv(self, timeout: float | None) -> Any:
        if not self._sock.poll(int(1000 * (self.timeout if timeout is None else timeout))):
            raise DaemonTimeout(f"no reply from {self.endpoint} within {self.timeout if timeout is None else timeout}"
                                " s (daemon not running, wrong endpoint, or key not allowed)")
        return msgpack.unpackb(self._sock.recv(), raw=False)

    def request(self, op: str, timeout: float | None = None, **fields: Any) -> dict[str, Any]:
        """Send one request and return the reply map, whatever its ``ok``."""
        rid = next(self._ids)
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        self._send(msgpack.packb({"op": op, "id": rid, **fields}, use_bin_type=True), timeout)
        while True:
            reply = self._recv(max(0.0, deadline - time.monotonic()))
            if isinstance(reply, dict) and reply.get("id") == rid:
                return reply  # stale replies of timed-out requests are skipped

    def call(self, op: str, timeout: float | None = None, **fields: Any) -> dict[str, Any]:
        """Send one request; return the reply or raise :class:`DaemonError`."""
        reply = self.request(op, timeout, **fields)
        if not reply.get("ok"):
            err = reply.get("error") or {}
            raise DaemonError(op, str(err.get("code")), str(err.get("message")))
        return reply

    def clock_offset(self, samples: int = 8) -> tuple[float, float]:
        """Estimate (daemon clock − local monotonic clock, round trip) from the best of ``samples`` exchanges."""
        best: tuple[float, float] | None = None
        for _ in range(samples):
            t0 = time.monotonic()
            r = self.call("clock", t_client=t0)
            t1 = time.monotonic()
            rtt = (t1 - t0) - (r["t_send"] - r["t_recv"])
            offset = 0.5 * ((r["t_recv"] - t0) + (r["t_send"] - t1))
            if best is None or rtt < best[1]:
                best = (offset, rtt)
        assert best is not None
        return best


class Telemetry:
    """SUB socket on the daemon's telemetry endpoint; yields ``(topic, message)`` pairs."""

    def __init__(self, endpoint: str = "tcp://127.0.0.1:5556", topics: tuple[bytes, ...] = (b"state", b"event"),
                 client_key: str | Path | None = None, server_key: str | Path | None = None) -> None:
        self._ctx = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        _curve_setup(self._sock, client_key, server_key)
        for t in topics:
            self._sock.setsockopt(zmq.SUBSCRIBE, t)
        self._sock.connect(endpoint)

    def close(self) -> None:
        self._sock.close(0)

    def __enter__(self) -> Telemetry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def recv(self, timeout: float = 1.0) -> tuple[str, dict[str, Any]] | None:
        """Next message, or None after ``timeout`` seconds."""
        if not self._sock.poll(int(timeout * 1000)):
            return None
        topic, payload = self._sock.recv_multipart()[:2]
        return topic.decode(), msgpack.unpackb(payload, raw=False)

    def iter(self, duration: float) -> Iterator[tuple[str, dict[str, Any]]]:
        """Messages for ``duration`` seconds."""
        end = time.monotonic() + duration
        while (left := end - time.monotonic()) > 0:
            msg = self.recv(left)
            if msg is not None:
                yield msg

    def wait_for(self, predicate: Any, timeout: float) -> tuple[str, Mapping[str, Any]] | None:
        """First message with ``predicate(topic, msg)`` true within ``timeout`` s, else None."""
        for topic, msg in self.iter(timeout):
            if predicate(topic, msg):
                return topic, msg
        return None
