"""A daemon on the sample head's emulated buses with show-control inputs from an ``[inputs]`` fragment."""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.runtime.conftest import SAMPLE

#: The emulated buses' patience, raised: these tests are about the inputs, and a loaded host stalls the emulators'
#: processes for seconds at a time (a lost heartbeat or a missed read would fault the head mid-test).
PATIENT = (("heartbeat_timeout_s = 1.0", "heartbeat_timeout_s = 5.0"), ("sdo_timeout_s = 1.0", "sdo_timeout_s = 5.0"),
           ("max_consecutive_failures = 20", "max_consecutive_failures = 500"),
           ("feedback_timeout_s = 1.0", "feedback_timeout_s = 5.0"), ("retries = 8", "retries = 10"))


#: How long an actuator of the patient head may exceed its following error (s).
PATIENT_FOLLOWING_S = 2.0


def started(make: Callable[[], Any], tries: int = 3) -> Any:
    """A started daemon from ``make()``; an emulated bus that fails to open on a loaded host gets another try."""
    from drivers.errors import BusError
    from runtime.daemon import DaemonStartError

    for k in range(tries):
        daemon = make()
        try:
            daemon.start()
            return daemon
        except (BusError, DaemonStartError):
            daemon.stop()
            if k == tries - 1:
                raise
            time.sleep(2.0)
    raise AssertionError("unreachable")


def enable(c: Any, tries: int = 3) -> None:
    """Enable the head, resetting a bus fault an emulator stalled by a loaded host caused (a few tries)."""
    from models.client import DaemonError

    for k in range(tries):
        s = c.call("status")
        if s["lifecycle"] in ("fault", "estop") or "fault" in s["buses"].values():
            c.call("reset")
        try:
            c.call("enable")
            return
        except DaemonError:
            if k == tries - 1:
                raise
            time.sleep(1.0)


def show_head(tmp: Path, fragment: str) -> Path:
    """The sample head with the ``[inputs]`` of ``fragment`` (TOML text) and patient emulated buses, under ``tmp``."""
    from runtime.inputs.headfile import head_with_inputs

    frag = tmp / "inputs.toml"
    frag.write_text(fragment)
    head = head_with_inputs(SAMPLE, frag, tmp / "head" / "head.toml")
    text = head.read_text()
    for old, new in PATIENT:
        text = text.replace(old, new)
    # Emulated drives starved on a loaded host lag a full-speed move (a timecode relocation) by more than 0.1 s of
    # travel for over the default half second, which the following-error watch rightly faults; here the examples
    # are under test, not the watch (tests/runtime/test_feedback_watch.py), so each actuator gets 2 s.
    text = text.replace("[[actuators]]\n", f"[[actuators]]\nfollowing_error_time_s = {PATIENT_FOLLOWING_S}\n")
    head.write_text(text)
    return head


def loopback_address() -> str:
    """A random loopback address other than 127.0.0.1 (sACN's port is fixed: each receiver gets its own address)."""
    return f"127.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"


class Events:
    """Telemetry events collected on a thread while a test runs."""

    def __init__(self, endpoint: str) -> None:
        from models.client import Telemetry

        self.items: list[dict[str, Any]] = []
        self._tel = Telemetry(endpoint, topics=(b"event",))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            got = self._tel.recv(0.2)
            if got is not None:
                self.items.append(got[1])

    def of(self, kind: str, **match: Any) -> list[dict[str, Any]]:
        return [e for e in list(self.items) if e["event"] == kind and all(e.get(k) == v for k, v in match.items())]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._tel.close()
