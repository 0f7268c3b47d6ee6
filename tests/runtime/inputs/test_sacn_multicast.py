"""The sACN input with ``multicast = true``: it joins the universe's group on the bind interface and takes what the
``sacn`` library's own sender multicasts to that universe (loopback), and nothing of another universe's group."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from runtime.core import commands as C
from runtime.inputs.config import SacnConfig, SlotMap
from runtime.inputs.sacn import SacnInput
from tests.runtime.inputs.test_pure import CHANNELS

PORT = 5568  # E1.31's port: the library's sender multicasts to it


def _multicast_on_loopback() -> bool:
    """Whether this host delivers a multicast datagram sent from loopback to a member on loopback."""
    group = "239.255.250.1"
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        rx.bind((group, 0))
        membership = socket.inet_aton(group) + socket.inet_aton("127.0.0.1")
        rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        rx.settimeout(1.0)
        tx.bind(("127.0.0.1", 0))
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        tx.sendto(b"probe", (group, rx.getsockname()[1]))
        return rx.recv(16) == b"probe"
    except OSError:
        return False
    finally:
        rx.close()
        tx.close()


def _sender(universe: int, jaw: float):
    import sacn

    sender = sacn.sACNsender(bind_address="127.0.0.1", bind_port=0, source_name="console", universeDiscovery=False,
                             fps=40)
    sender.start()
    sender.activate_output(universe)
    sender[universe].multicast = True
    raw = round(jaw / 20.0 * 65535)
    sender[universe].dmx_data = (raw >> 8, raw & 0xFF) + (0,) * 510
    return sender


@pytest.mark.skipif(not _multicast_on_loopback(), reason="this host does not deliver multicast on loopback")
def test_a_multicast_receiver_takes_its_universes_group_only() -> None:
    got: list[C.Live] = []
    cfg = SacnConfig("127.0.0.1", PORT, 7, (SlotMap("jaw", 0, 16, 0.0, 20.0),), "htp", 2.5, multicast=True)
    rx = SacnInput(cfg, CHANNELS, got.append)
    rx.start()
    other = _sender(8, jaw=9.0)  # another universe's group: never seen
    mine = _sender(7, jaw=5.0)
    try:
        deadline = time.monotonic() + 20.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
        assert got, "no multicast packet of universe 7 reached the input"
        assert rx.bound["bind"] == "239.255.0.7:5568"
        live = got[-1]
        assert live.source == "sacn" and list(live.channels) == [CHANNELS.index_of("jaw")]
        np.testing.assert_allclose(live.values, [5.0], atol=20.0 / 65535)
        time.sleep(0.3)
        assert all(abs(c.values[0] - 5.0) < 1e-3 for c in got)  # universe 8 joined nobody here
        assert "another universe" not in str(rx.refusals.snapshot())
    finally:
        mine.stop()
        other.stop()
        rx.close()
