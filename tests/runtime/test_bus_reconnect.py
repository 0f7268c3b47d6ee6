"""A bus whose transport goes away (emulator process killed: the socketcand server, the Dynamixel pseudo-terminal)
faults naming it while the loop and telemetry keep running; the bus process reconnects in the background with
backoff, and once the emulator is back the first ``reset`` succeeds and ``enable`` resumes motion, with no daemon
restart. Waits are generous: the host may be a loaded two-core machine."""

from __future__ import annotations

import math

import pytest

from models.client import Client, DaemonError, Telemetry
from tests._wait import wait_until
from tests.runtime.conftest import enable_retrying


def _status(c: Client) -> dict:
    return c.call("status")


def _truth_deg(daemon, name: str) -> float:
    return math.degrees(daemon.hw.simulated_positions()[name])


def _arrives(daemon, c: Client, name: str, want: float, tol: float = 0.5, timeout: float = 6.0) -> bool:
    def there() -> bool:
        measured = _status(c)["measured"][name]
        return measured is not None and abs(measured - want) < tol and abs(_truth_deg(daemon, name) - want) < tol

    return bool(wait_until(there, timeout))


@pytest.mark.parametrize(("bus", "other", "actuator"), [("can0", "dxl", "jaw"), ("dxl", "can0", "brow_l")])
def test_a_lost_bus_reconnects_after_its_emulator_restarts(make_daemon, bus: str, other: str, actuator: str) -> None:
    d = make_daemon()
    with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint) as tel, \
            Telemetry(d.telemetry_endpoint, topics=(b"event",)) as events:
        sim = d.hw.emulator(bus)
        for attempt in range(2):
            enable_retrying(c)
            c.call("pose", pose={actuator: 5.0}, speed=1.0)
            assert _arrives(d, c, actuator, 5.0)
            sim.kill()  # the device server goes away: socketcand connection dropped / pseudo-terminal gone
            ev = tel.wait_for(lambda topic, m: topic == "event" and m["event"] == "fault", 30)
            assert ev is not None, "no fault event after the emulator died"
            if ev[1]["bus"] == bus or attempt == 1:
                break
            # the other bus faulted first (its emulator starved of CPU on a loaded host): start over
            sim.restart()
            wait_until(lambda: c.request("reset", timeout=30)["ok"], 30, interval=0.5)
            while events.recv(0.05) is not None:
                pass

        # fault naming the bus; the other bus is torqued off; telemetry keeps coming
        assert ev[1]["bus"] == bus and f"bus {bus}" in ev[1]["message"], ev[1]
        st = wait_until(lambda: (s := _status(c))["buses"][other] == "inactive" and s["connected"][bus] is False
                        and s, 30)
        # (on a loaded host, stale feedback or the driver's missed replies may be noticed before the lost port)
        assert st and st["lifecycle"] == "fault" and st["fault"]["bus"] == bus
        assert st["fault"]["source"] in ("bus", "driver", "timeout")
        assert st["connected"][bus] is False and st["connected"][other] is True
        assert st["connection"][bus]["state"] in ("lost", "reconnecting")
        # the bus process keeps trying, with growing waits: attempts and the connection state show in telemetry
        # (a snapshot taken before the fault may be published after its event: the events and the state snapshots
        # are published by different threads of the server)
        states = [m for topic, m in tel.iter(2.5) if topic == "state" and m["t"] >= ev[1]["t"]]
        assert len(states) >= 5, "telemetry went silent"
        assert {m["connection"][bus]["state"] for m in states} <= {"lost", "reconnecting"}
        assert max(m["connection"][bus]["attempts"] for m in states) >= 2
        assert all(m["lifecycle"] == "fault" for m in states)
        # reset cannot succeed while the bus is unreachable
        with pytest.raises(DaemonError) as info:
            c.call("reset", timeout=30)
        assert info.value.code == "hardware" and bus in str(info.value)

        sim.restart()  # the device server is back, where it was
        assert c.call("reset", timeout=30)["lifecycle"] == "inactive"  # the first reset after it is reachable
        st = _status(c)
        assert st["connected"][bus] is True and st["connection"][bus]["state"] == "connected"
        assert st["fault"] is None
        c.call("enable", timeout=30)
        # the restarted emulator's devices booted at neutral: a real move to a new target
        c.call("pose", pose={actuator: 3.0}, speed=1.0)
        assert _arrives(d, c, actuator, 3.0), "motion did not resume after reconnecting"
        # each change of the connection state was announced
        links = [(m["bus"], m["state"]) for _, m in events.iter(0.5) if m["event"] == "bus_link"]
        assert links[0] == (bus, "lost") and links[-1] == (bus, "connected") and (bus, "reconnecting") in links
        c.call("disable")


def test_the_core_faults_on_a_lost_bus_even_inactive_and_reports_each_connection_change() -> None:
    """The core alone, stepped with bus feedback as the bus processes publish it."""
    from runtime.core import commands as C
    from runtime.core.cycle import BusInput
    from runtime.core.lifecycle import Lifecycle
    from tests.runtime.test_core import Rig

    rig = Rig()
    rig.cycle()
    link = {"can0": ("connected", 0, math.inf)}

    def inputs() -> tuple[BusInput, ...]:
        out = []
        for b, idx in rig.params.buses:
            state, attempts, retry_at = link.get(b, ("connected", 0, math.inf))
            out.append(BusInput(b, "fault" if state != "connected" else rig.bus_state[b], state == "connected",
                                  rig.q[idx].copy(), rig.t, {}, state, attempts, retry_at))
        return tuple(out)

    rig.bus_inputs = inputs  # type: ignore[method-assign]
    rig.cycle()
    assert rig.state.lifecycle is Lifecycle.INACTIVE
    link["can0"] = ("lost", 0, rig.t + 0.25)
    out = rig.cycle()
    assert rig.state.lifecycle is Lifecycle.FAULT
    fault = next(e for e in out.events if e["event"] == "fault")
    assert fault["source"] == "bus" and fault["bus"] == "can0"
    assert fault["message"].startswith("bus can0: connection lost")
    assert ("can0", "lost") in [(e["bus"], e["state"]) for e in out.events if e["event"] == "bus_link"]
    status = rig.call(C.Status)
    assert status["connection"]["can0"]["state"] == "lost" and status["connection"]["can0"]["retry_in_s"] <= 0.25
    link["can0"] = ("reconnecting", 1, math.inf)
    events = rig.cycle().events
    assert [(e["state"], e["attempts"]) for e in events if e["event"] == "bus_link"] == [("reconnecting", 1)]
    link["can0"] = ("connected", 1, math.inf)
    events = rig.cycle().events
    assert [e["state"] for e in events if e["event"] == "bus_link"] == ["connected"]
    assert rig.call(C.Reset)["lifecycle"] == "inactive"
    assert rig.call(C.Enable)["lifecycle"] == "active"

