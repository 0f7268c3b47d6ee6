"""The protocol fuzzed with hypothesis: malformed, oversized and hostile requests never crash the daemon and never
command a motor outside its limits (checked on the daemon's commands and on the emulators' ground truth)."""

from __future__ import annotations

import math
import threading

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.client import Client
from runtime.daemon import Daemon
from runtime.messages import OPS as KNOWN_OPS

OPS = sorted(KNOWN_OPS)
CHANNELS = ["jaw", "blink", "brow_l", "lid_r", "lip_corner_l", "cheek_r", "nose", "", "arkit.jawOpen"]
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.sampled_from([0.0, 1e308, -1e308, 1e-320, 28.0, -2.0, 45.0]),
)
SCALARS = st.one_of(st.none(), st.booleans(), NUMBERS, st.text(max_size=20), st.binary(max_size=20))
ANY = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=5)), max_leaves=20)
KEYS = st.lists(st.lists(NUMBERS, min_size=0, max_size=7), max_size=6)
CLIP = st.fixed_dictionaries({
    "name": st.one_of(st.text(max_size=10), ANY),
    "channels": st.dictionaries(st.sampled_from(CHANNELS), st.fixed_dictionaries(
        {"keys": st.one_of(KEYS, ANY)}, optional={"interp": st.sampled_from(["step", "linear", "bezier", "x"])}),
        max_size=4),
})
FIELDS = st.dictionaries(
    st.sampled_from(["clip", "at", "from", "speed", "loop", "time", "channels", "frames", "pose", "reason",
                     "action", "name", "t_client", "bogus"]),
    st.one_of(ANY, CLIP, st.sampled_from(["probe", "start", "stop"]), KEYS,
              st.dictionaries(st.sampled_from(CHANNELS), NUMBERS, max_size=4),
              st.lists(st.sampled_from(CHANNELS), max_size=4)),
    max_size=4,
)
REQUEST = st.one_of(
    ANY,
    st.builds(lambda op, rid, f: {"op": op, "id": rid, **f}, st.sampled_from([*OPS, "dance", ""]),
              st.one_of(st.integers(min_value=-(2**63), max_value=2**64 - 1), st.text(max_size=200), ANY), FIELDS),
)


def _check_limits(daemon: Daemon) -> None:
    assert daemon.state is not None
    sf = daemon.state.safety
    q = sf.q.copy()
    assert np.all(np.isfinite(q))
    assert np.all(q >= sf.lo - 1e-12) and np.all(q <= sf.hi + 1e-12)


@pytest.fixture(scope="module")
def fuzz_daemon(shared_daemon):
    d = shared_daemon
    d.call("enable")
    with Client(d.command_endpoint, timeout=30) as c:
        d.fuzz_client = c
        yield d
    d.call("disable")


def _recover(daemon: Daemon) -> None:
    c = daemon.fuzz_client
    status = c.call("status")
    if status["lifecycle"] in ("estop", "fault"):
        assert (status.get("fault") or {}).get("source") != "driver", status["fault"]  # a driver guard refused
        c.call("reset")
        status = c.call("status")
    if status["lifecycle"] == "inactive":
        c.call("enable")


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(msg=REQUEST)
def test_any_request_gets_a_reply_and_limits_hold(fuzz_daemon: Daemon, msg) -> None:
    reply = fuzz_daemon.fuzz_client.send_raw(msgpack.packb(msg, use_bin_type=True))
    assert isinstance(reply, dict) and isinstance(reply.get("ok"), bool) and "id" in reply
    if not reply["ok"]:
        assert reply["error"]["code"] in ("bad_request", "unknown_op", "bad_value", "unknown_channel", "not_found",
                                          "bad_state", "estop", "fault", "too_large", "hardware")
    msgpack.packb(reply)  # every reply is sendable
    _check_limits(fuzz_daemon)
    _recover(fuzz_daemon)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(payload=st.one_of(st.binary(max_size=300), REQUEST.map(lambda m: msgpack.packb(m, use_bin_type=True))))
def test_raw_bytes_over_the_socket(fuzz_daemon: Daemon, payload: bytes) -> None:
    with Client(fuzz_daemon.command_endpoint, timeout=30) as c:
        reply = c.send_raw(payload)
    assert isinstance(reply, dict) and isinstance(reply["ok"], bool)
    _check_limits(fuzz_daemon)
    _recover(fuzz_daemon)


def test_hostile_streams_never_leave_limits(fuzz_daemon: Daemon) -> None:
    """Extreme but finite frames at full rate: motion is clipped and rate-limited, ground truth stays in range."""
    d = fuzz_daemon
    _recover(d)
    names = list(d.names)
    stop = threading.Event()
    worst: list[float] = []

    def watch() -> None:
        while not stop.is_set():
            truth = d.hw.simulated_positions()
            worst.append(max(max(a.min - truth[a.name], truth[a.name] - a.max) for a in d.head.actuators
                             if a.name in truth))
            stop.wait(0.01)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        with Client(d.command_endpoint, timeout=30) as c:
            t0 = c.call("clock")["t_send"]
            rng = np.random.default_rng(7)
            for k in range(60):
                values = rng.choice([-1e6, 1e6, 0.0, 1e300, -1e300], size=len(names)).tolist()
                r = c.call("stream", channels=names, frames=[[t0 + 0.01 * k, *values]])
                assert r["accepted"] + r["late"] == 1
        _check_limits(d)
    finally:
        stop.set()
        watcher.join()
    # Ground truth never beyond a limit by more than the drives' own tracking overshoot.
    assert max(worst) < math.radians(1.0)
    status = d.fuzz_client.call("status")
    assert status["lifecycle"] == "active" and status["fault"] is None
