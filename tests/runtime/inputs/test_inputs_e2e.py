"""End to end: each show-control input driven by its library's own sender over loopback, against a daemon on the
sample head's emulated buses. Waits are generous (the host may be a loaded two-core machine); nothing is timed."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from models.client import Client
from tests._wait import wait_until
from tests.runtime.inputs.conftest import Events, enable, loopback_address, show_head, started

FRAGMENT = """
[inputs.osc]
bind = "127.0.0.1:0"
tcp = "127.0.0.1:0"
control_allow = ["127.0.0.1"]
[inputs.osc.map]
"/face/jaw" = "jaw"
"/face/brow/*" = "brow_*"

[inputs.sacn]
bind = "{sacn}"
universe = 3
start = 101
merge = "htp"
[[inputs.sacn.slots]]
channel = "jaw"
bits = 16
range = [0.0, 20.0]
[[inputs.sacn.slots]]
channel = "brow_r"
range = [0.0, 25.5]

[inputs.timecode]
bind = "127.0.0.1:0"
rate = "25"
freewheel_s = 1.0
lock_samples = 3
[inputs.timecode.clips]
ramp = "00:10:00:00"
"""
RAMP = {"name": "ramp", "channels": {"jaw": {"interp": "linear", "keys": [[0, 0], [20, 20]]}}}


@pytest.fixture(scope="module")
def show(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One daemon with all three inputs (tests leave it inactive)."""
    from models.headspec import load_head
    from runtime.daemon import Daemon
    from tests.runtime.conftest import daemon_overrides

    tmp = tmp_path_factory.mktemp("show")
    head = show_head(tmp, FRAGMENT.replace("{sacn}", loopback_address()))
    # The OSC input uses the stream watchdog's times: generous here, so a stalled loaded host never trips it.
    overrides = daemon_overrides(tmp, **{"safety.watchdog_hold_s": 1.0, "safety.watchdog_neutral_s": 3.0,
                                             "safety.feedback_timeout_s": 5.0})
    daemon = started(lambda: Daemon(load_head(head), overrides, target_solvers=()))
    try:
        yield daemon
    finally:
        daemon.stop()


def _status(c: Client) -> dict:
    return c.call("status")


def _near(c: Client, **want: float) -> dict | None:
    s = _status(c)
    ok = all(abs(s["commanded"][k] - v) < 0.05 for k, v in want.items())
    return s if ok else None


def _brief(c: Client) -> str:
    """The parts of ``status`` an assertion message needs."""
    s = _status(c)
    keys = ("lifecycle", "mode", "source", "fault", "guard", "live", "clock", "timeline", "inputs")
    commanded = {k: round(v, 3) for k, v in s["commanded"].items() if k in ("jaw", "brow_l", "brow_r")}
    return repr({k: s.get(k) for k in keys} | {"commanded": commanded})


def _settled_updates(c: Client) -> int:
    """The live input's update count once it has stopped changing (packets still in flight have landed)."""
    last = -1
    while True:
        time.sleep(0.3)
        n = _status(c)["live"]["updates"]
        if n == last:
            return n
        last = n


def _inactive(c: Client) -> None:
    s = _status(c)
    if s["lifecycle"] in ("fault", "estop") or "fault" in s["buses"].values():
        c.call("reset")
    if _status(c)["lifecycle"] == "active":
        c.call("disable")


class Repeat:
    """Calls ``send`` every ``period`` s on a thread until closed (a sender that streams continuously)."""

    def __init__(self, send: Any, period: float = 0.02) -> None:
        self.send = send
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            with contextlib.suppress(OSError):  # a full socket buffer on a loaded host: the next one goes
                self.send()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


# ---------------------------------------------------------------------- OSC
def test_osc_messages_and_bundles_move_the_head(show) -> None:
    from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
    from pythonosc.osc_message_builder import OscMessageBuilder
    from pythonosc.udp_client import SimpleUDPClient

    with Client(show.command_endpoint, timeout=30) as c:
        hello = c.call("hello")
        host, port = hello["inputs"]["osc"]["udp"].rsplit(":", 1)
        osc = SimpleUDPClient(host, int(port))
        for _ in range(3):  # an emulator stalled by a loaded host can fail an enable: reset, try again
            _inactive(c)
            osc.send_message("/likeness/enable", [])  # a control address, allowed for 127.0.0.1
            with contextlib.suppress(AssertionError):
                wait_until(lambda: _status(c)["lifecycle"] == "active", 30)
                break
        assert _status(c)["lifecycle"] == "active", _brief(c)
        rep = Repeat(lambda: osc.send_message("/face/jaw", 6.0))
        try:
            s = wait_until(lambda: _near(c, jaw=6.0), 30)
            assert s and s["mode"] == "live" and s["source"] == "osc", s
        finally:
            rep.close()

        def bundle(jaw: float, brow: float) -> Any:
            b = OscBundleBuilder(IMMEDIATELY)
            for address, value in (("/face/jaw", jaw), ("/face/brow/l", brow), ("/face/brow/r", brow)):
                m = OscMessageBuilder(address)
                m.add_arg(value)
                b.add_content(m.build())
            return b.build()

        before = _settled_updates(c)
        osc.send(bundle(2.0, 7.5))
        s = wait_until(lambda: _near(c, jaw=2.0, brow_l=7.5, brow_r=7.5), 30)
        assert s, _brief(c)
        assert s["live"]["updates"] == before + 1  # three messages, one update: applied together
        refused = s["inputs"]["osc"]["refused"]
        osc.send_message("/face/nose", 1.0)  # unmapped: refused and counted, nothing moves
        osc.send_message("/face/jaw", "wide")
        assert wait_until(lambda: len(_status(c)["inputs"]["osc"]["refused"]) >= len(refused) + 2, 30)
        assert _near(c, jaw=2.0)
        # OSC 1.1 over TCP (SLIP framing) reaches the same map
        from pythonosc.tcp_client import SimpleTCPClient

        host, port = hello["inputs"]["osc"]["tcp"].rsplit(":", 1)
        tcp = SimpleTCPClient(host, int(port))
        try:
            tcp.send_message("/face/jaw", 3.5)
            wait_until(lambda: _near(c, jaw=3.5), 30, lambda: f"jaw near 3.5; {_brief(c)}")
        finally:
            tcp.close()
        osc.send_message("/likeness/estop", ["stage manager"])
        s = wait_until(lambda: _status(c)["lifecycle"] == "estop" and _status(c), 30)
        assert s and s["estop"] == "stage manager"
        _inactive(c)


def test_packets_the_core_refuses_are_counted_under_its_reason_each_time(show) -> None:
    """A live packet crosses to the core unanswered unless refused; every refusal comes back to its input."""
    from pythonosc.udp_client import SimpleUDPClient

    with Client(show.command_endpoint, timeout=30) as c:
        host, port = c.call("hello")["inputs"]["osc"]["udp"].rsplit(":", 1)
        _inactive(c)
        before = _status(c)["inputs"]["osc"]["refused"].get("bad_state", 0)
        osc = SimpleUDPClient(host, int(port))
        for v in (1.0, 2.0, 3.0):  # the head is inactive: the core refuses each
            osc.send_message("/face/jaw", v)
        assert wait_until(lambda: _status(c)["inputs"]["osc"]["refused"].get("bad_state", 0) >= before + 3, 30)
        assert _status(c)["lifecycle"] != "active"


# ---------------------------------------------------------------------- sACN
def _sender(name: str, dest: str, priority: int, jaw: float, brow: float) -> Any:
    import sacn

    sender = sacn.sACNsender(bind_address="127.0.0.1", bind_port=0, source_name=name, universeDiscovery=False,
                             fps=40)
    sender.start()
    sender.activate_output(3)
    out = sender[3]
    out.multicast = False
    out.destination = dest
    out.priority = priority
    _set(sender, jaw, brow)
    return sender


def _set(sender: Any, jaw: float, brow: float) -> None:
    raw = round(jaw / 20.0 * 65535)
    data = [0] * 512
    data[100], data[101], data[102] = raw >> 8, raw & 0xFF, round(brow / 25.5 * 255)  # start address 101
    sender[3].dmx_data = tuple(data)


def test_sacn_sources_merge_by_priority_then_htp_and_silence_trips_the_watchdog(show) -> None:
    with Client(show.command_endpoint, timeout=30) as c:
        dest = c.call("hello")["inputs"]["sacn"]["bind"].rsplit(":", 1)[0]
        _inactive(c)  # whatever an earlier test left
        enable(c)
        events = Events(show.telemetry_endpoint)
        # (small moves: the skin-strain guard lets them through whole)
        a = _sender("console A", dest, 100, jaw=2.0, brow=3.0)
        b = _sender("console B", dest, 100, jaw=4.0, brow=1.5)
        try:
            # the same priority: the highest value of each slot (HTP)
            s = wait_until(lambda: _near(c, jaw=4.0, brow_r=3.0), 30)
            assert s and s["mode"] == "live" and s["source"] == "sacn", _brief(c)
            assert len(s["inputs"]["sacn"]["sources"]) == 2
            # a higher priority: that source alone
            b[3].priority = 150
            _set(b, jaw=3.0, brow=1.0)
            wait_until(lambda: _near(c, jaw=3.0, brow_r=1.0), 30, lambda: f"jaw 3, brow_r 1; {_brief(c)}")
            # B falls silent: after E1.31's data loss time A, still sending, takes over
            b.stop()
            wait_until(lambda: _near(c, jaw=2.0, brow_r=3.0), 30, lambda: f"jaw 2, brow_r 3; {_brief(c)}")
            # every source silent: the watchdog holds, then eases to neutral
            a.stop()
            wait_until(lambda: events.of("watchdog", stage="neutral"), 30,
                       lambda: f"a neutral watchdog event in {events.items}")
            assert events.of("watchdog", stage="hold", source="sacn")
            s = wait_until(lambda: _near(c, jaw=0.0, brow_r=0.0), 30)
            assert s and s["mode"] == "neutral", _brief(c)
        finally:
            a.stop()
            b.stop()
            events.close()
        _inactive(c)


# ---------------------------------------------------------------------- MIDI timecode
def test_mtc_locks_freewheels_then_holds_and_a_jump_relocates_the_clip(show) -> None:
    with Client(show.command_endpoint, timeout=30) as c:
        host, port = c.call("hello")["inputs"]["timecode"]["bind"].rsplit(":", 1)
        _inactive(c)  # whatever an earlier test left
        enable(c)
        c.call("load_clip", clip=RAMP)
        events = Events(show.telemetry_endpoint)
        import mido.sockets

        from runtime.inputs.mtcgen import MtcGenerator

        gen = MtcGenerator(mido.sockets.connect(host, int(port)), "25")
        try:
            gen.roll(600.0 + 2.0)  # 00:10:02:00: two seconds into the chased clip
            s = wait_until(lambda: _status(c)["clock"]["state"] == "locked" and _status(c), 30)
            assert s and s["clock"]["rate"] == "25" and s["clock"]["source"] == "mtc", _brief(c)
            s = wait_until(lambda: (st := _status(c))["source"] == "timecode" and st, 30)
            assert s and s["mode"] == "clip" and s["timeline"]["clip"] == "ramp", s
            # the clip follows the timecode: clip time = timecode - 10 min, the jaw on the ramp
            s = _status(c)
            tc = s["clock"]["seconds"]
            assert s["timeline"].get("time", -1.0) == pytest.approx(tc - 600.0, abs=0.3), _brief(c)
            assert wait_until(lambda: abs((st := _status(c))["commanded"]["jaw"] - st["timeline"]["time"]) < 0.5,
                              30), _brief(c)
            # a 2 s dropout: freewheel (1 s, freewheel_s), then hold
            at_halt = _status(c)["timeline"]["time"]
            gen.halt()
            time.sleep(2.0)
            wait_until(lambda: events.of("timecode", change="hold"), 30,
                       lambda: f"a timecode hold event in {events.items}")
            assert events.of("timecode", change="freewheel")
            held = _status(c)["timeline"].get("time")
            assert held is not None, _brief(c)
            assert 0.5 < held - at_halt < 1.3, (at_halt, held)  # it ran on for freewheel_s, then stopped
            time.sleep(0.5)
            s = _status(c)
            assert s["clock"]["state"] == "hold" and s["timeline"].get("time", -1.0) == pytest.approx(held), _brief(c)
            # timecode runs again elsewhere: it relocks there, and the clip relocates
            gen.roll(600.0 + 12.0)
            s = wait_until(lambda: (st := _status(c))["clock"]["state"] == "locked" and st, 30)
            assert s, _brief(c)
            assert s["timeline"].get("time", -1.0) == pytest.approx(s["clock"]["seconds"] - 600.0, abs=0.3), _brief(c)
            assert s["timeline"].get("time", -1.0) > 11.0, _brief(c)
            # a jump while running relocates the clip at once
            jumps = len(events.of("timecode", change="jump"))
            gen.roll(600.0 + 5.0)
            wait_until(lambda: len(events.of("timecode", change="jump")) > jumps, 30,
                       lambda: f"a timecode jump event in {events.items}")
            s = _status(c)
            assert s["timeline"].get("time", -1.0) == pytest.approx(s["clock"]["seconds"] - 600.0, abs=0.3), _brief(c)
            assert s["timeline"].get("time", -1.0) < 8.0, _brief(c)
            assert wait_until(lambda: _status(c)["commanded"]["jaw"] < 8.5, 30)
        finally:
            gen.close()
            events.close()
        _inactive(c)
