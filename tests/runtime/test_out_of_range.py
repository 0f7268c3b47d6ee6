"""A motor found outside its configured limits when the head enables: emulated CANopen drives (the jaw below its
range, a lip corner above it) start out of range; enabling keeps them where they stand (no jump the drivers would
refuse), publishes an ``out_of_range`` event naming each, brings each back into range at safe speed, never further
out, and says when each is inside again. The drivers' own guard takes a target outside the limits only as a move
back toward them. A Dynamixel servo cannot be brought back so (its own limit registers clamp every goal into range:
it would jump), so its driver refuses to enable it, naming it.

Every wait is an event or a state with a generous overall timeout (a loaded 2-core host starves the emulators)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest

from drivers.base import MotorBus, MotorConfig, MotorState
from drivers.errors import CommandRejected
from models.client import Client, Telemetry
from tests.runtime.conftest import SAMPLE, daemon_overrides, enable_retrying

START_DEG = {"jaw": -39.9, "lip_corner_l_up": 45.0}  # CANopen drives; ranges -2..28° and -30..40°
LIMITS = {"jaw": (-2.0, 28.0), "lip_corner_l_up": (-30.0, 40.0)}


class _Bus(MotorBus):
    """A bus with no device behind it: what the base class's guard lets through is recorded."""

    def __init__(self, motors: list[MotorConfig], at: dict[str, float]) -> None:
        super().__init__("test", {}, motors)
        self.at = dict(at)
        self.sent: list[dict[str, float]] = []

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _enable(self) -> None:
        pass

    def _disable(self) -> None:
        pass

    def _reset_fault(self) -> None:
        pass

    def _on_fault(self) -> None:
        pass

    def _write(self, targets: dict[str, float]) -> None:
        self.sent.append(dict(targets))
        self.at.update(targets)

    def _read(self) -> dict[str, MotorState]:
        now = time.monotonic()
        return {n: MotorState(p, 0.0, 0.0, 0, 0, True, now) for n, p in self.at.items()}


def test_driver_guard_takes_only_moves_back_toward_the_range() -> None:
    motor = MotorConfig("jaw", 1, 1000.0, min_position=-0.035, max_position=0.49, max_velocity=1.0)
    bus = _Bus([motor], {"jaw": math.radians(-39.9)})
    bus.open()
    bus.enable()
    held = bus.last_commands()["jaw"]
    t = time.monotonic() + 0.01
    with pytest.raises(CommandRejected, match="not toward it"):
        bus.write({"jaw": held - 0.001}, stamp=t)  # further out
    with pytest.raises(CommandRejected, match="exceeds max_velocity"):
        bus.write({"jaw": -0.035}, stamp=t)  # back into range in one jump
    bus.write({"jaw": held + 0.005}, stamp=t)  # toward the range within the rate: taken
    bus.write({"jaw": held + 0.005}, stamp=t + 0.004)  # holding out there: taken
    with pytest.raises(CommandRejected, match="not toward it"):
        bus.write({"jaw": held + 0.004}, stamp=t + 0.008)  # what it came back, it cannot go out again
    assert [s["jaw"] for s in bus.sent] == [held + 0.005, held + 0.005]


@pytest.mark.exclusive
def test_motors_enabled_out_of_range_are_brought_back(tmp_path: Path) -> None:
    from models.headspec import load_head
    from runtime.daemon import Daemon
    from runtime.hardware import Hardware

    head = load_head(SAMPLE)
    hw = Hardware.from_head(head, initial={n: math.radians(v) for n, v in START_DEG.items()})
    d = Daemon(head, daemon_overrides(tmp_path), hardware=hw)
    try:
        d.start()
        with Client(d.command_endpoint, timeout=30) as c, Telemetry(d.telemetry_endpoint) as tel:
            enable_retrying(c)
            events: list[dict] = []
            extreme = dict(START_DEG)  # the furthest out each was measured or commanded
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline:
                msg = tel.recv(0.2)
                if msg is None:
                    continue
                topic, body = msg
                if topic == "event":
                    events.append(dict(body))
                    assert body["event"] != "fault", body
                elif topic == "state":
                    for name, start in START_DEG.items():
                        pick = min if start < LIMITS[name][0] else max
                        extreme[name] = pick(extreme[name], body["measured"][name], body["commanded"][name])
                inside = {e["actuator"] for e in events if e["event"] == "out_of_range" and e["state"] == "inside"}
                if inside == set(START_DEG):
                    break
            found = {e["actuator"]: e for e in events if e["event"] == "out_of_range" and e["state"] == "outside"}
            assert set(found) == set(START_DEG), events
            jaw = found["jaw"]
            assert jaw["position"] == pytest.approx(-39.9, abs=0.1) and jaw["min"] == pytest.approx(-2.0), jaw
            back = {e["actuator"]: e for e in events if e["event"] == "out_of_range" and e["state"] == "inside"}
            assert set(back) == set(START_DEG), f"not back in range within 60 s; events: {events}"
            status = c.call("status")
            assert status["lifecycle"] == "active", status
            for name, start in START_DEG.items():
                lo, hi = LIMITS[name]
                side = -1.0 if start < lo else 1.0
                # never further out than where it stood (an encoder count's rounding aside)
                assert side * (extreme[name] - start) <= 0.05, (name, extreme[name])
                assert lo - 1e-6 <= back[name]["position"] <= hi + 1e-6, back[name]
                took = back[name]["t"] - found[name]["t"]
                print(f"\n{name}: enabled at {found[name]['position']:.1f}° (range {lo:g}..{hi:g}°), back in range "
                      f"after {took:.2f} s")
            # and then it is commanded as usual: a pose inside the range is reached
            c.call("pose", pose={"jaw": 4.0, "lip_corner_l_up": 0.0})
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline and abs(c.call("status")["commanded"]["jaw"] - 4.0) > 0.01:
                time.sleep(0.1)
            assert c.call("status")["commanded"]["jaw"] == pytest.approx(4.0, abs=0.01)
    finally:
        d.stop()
        hw.stop()


@pytest.mark.exclusive
def test_dynamixel_servo_out_of_range_is_not_enabled(tmp_path: Path) -> None:
    from models.client import DaemonError
    from models.headspec import load_head
    from runtime.daemon import Daemon
    from runtime.hardware import Hardware

    head = load_head(SAMPLE)
    hw = Hardware.from_head(head, initial={"cheek_l": math.radians(-40.0)})  # range -25..35°
    d = Daemon(head, daemon_overrides(tmp_path), hardware=hw)
    try:
        d.start()
        with Client(d.command_endpoint, timeout=30) as c:
            with pytest.raises(DaemonError, match=r"cheek_l: present position .* is outside"):
                c.call("enable", timeout=30)
            assert c.call("status")["lifecycle"] != "active"
    finally:
        d.stop()
        hw.stop()
