"""The protocol client's timeout covers sending: a DEALER whose peer refuses its handshake must not block."""

from __future__ import annotations

import time

import pytest
import zmq

from models.client import Client, DaemonTimeout


def test_a_refused_handshake_times_out_on_every_call_instead_of_blocking():
    """A plaintext client against a CURVE server: the server drops each connection at the handshake, so between
    reconnects the client's socket has no peer, where a plain send would block for good. Every call ends in
    :class:`DaemonTimeout` within about its timeout."""
    ctx = zmq.Context.instance()
    server = ctx.socket(zmq.ROUTER)
    server.setsockopt(zmq.LINGER, 0)
    public, secret = zmq.curve_keypair()
    server.curve_server = True
    server.curve_secretkey = secret
    server.curve_publickey = public
    port = server.bind_to_random_port("tcp://127.0.0.1")
    try:
        with Client(f"tcp://127.0.0.1:{port}", timeout=0.2) as c:
            c._sock.setsockopt(zmq.RECONNECT_IVL, 50)
            for _ in range(15):
                t0 = time.monotonic()
                with pytest.raises(DaemonTimeout):
                    c.call("hello")
                assert time.monotonic() - t0 < 1.0
    finally:
        server.close(0)
