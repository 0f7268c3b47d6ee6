"""A bounded, seeded fuzz run against a real daemon on emulated buses (part of ``make test``).

A few thousand requests: random msgpack values and bytes, mutations of a valid request of every op (fields dropped,
added, retyped; huge numbers, NaN and infinities; corrupted ids; nesting 40 to 1,000 deep), truncated messages,
oversize requests and multipart messages. They are sent in pipelined batches; after each batch the head is brought
back to active. Asserted: every request is answered (a reply carrying its id, or for a request whose id cannot be
read an error with a documented code), every target posted to a bus stays within the actuators' limits and velocity
(checked where the daemon hands targets to the bus processes) and the emulated motors stay within their limits, and
the API server process's memory stays bounded. ``LIKENESS_FUZZ_SEED`` replays a run; a failure prints its seed.
"""

from __future__ import annotations

import math
import os
import random
import time
from collections import Counter
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq

from models.client import Client
from models.protocol import ERROR_CODES
from runtime.hardware import motor_config
from runtime.messages import OPS

SEED = int(os.environ.get("LIKENESS_FUZZ_SEED", str(random.SystemRandom().randrange(1 << 31))))
REQUESTS = 3000
BATCH = 100
#: The head is brought back to active (reset, enable) after every this many batches (recovering costs bus time).
RECOVER_EVERY = 1
#: Ops that stop the head are drawn less often, so that most requests meet an active head.
RARE_OPS = ("estop", "disable", "reset")
MIB = 1 << 20
#: The API server (and its decoder) may grow by at most this much during the run.
RSS_GROWTH_BOUND = 150 * MIB

NASTY: list[Any] = [None, True, False, -1, 0, 2**63 - 1, -(2**63), 2**64 - 1, 1e308, -1e308, 5e-324,
                    float("nan"), float("inf"), float("-inf"), "", "x" * 3000, "\u202e\U0001f600", b"\x00\xff" * 8,
                    [], {}, [[1.0, 2.0]] * 3, {"a": {"b": [1]}}, [float("nan")] * 4]
CHANNELS = ["jaw", "brow_l", "lid_r", "cheek_l", "blink", "nose", "", "arkit.jawOpen", "lip_corner_l_up"]


class PostCheck:
    """Wraps a bus link's ``post``: every target must be finite, within limits (or, for an actuator found outside
    them, on its way back) and (between consecutive cycles) within the actuators' velocity limits."""

    def __init__(self, link: Any, period: float) -> None:
        self.link = link
        motors = [link.motors[n] for n in link.actuators]
        self.lo = np.array([m.min_position for m in motors])
        self.hi = np.array([m.max_position for m in motors])
        self.vmax = np.array([m.max_velocity for m in motors])
        self.period = period
        self.last: tuple[np.ndarray, float] | None = None
        self.posts = 0
        self.violations: list[str] = []
        self._post = link.post
        link.post = self.post

    def post(self, targets: np.ndarray, stamp: float | None = None) -> None:
        t = time.monotonic() if stamp is None else stamp
        q = np.array(targets, dtype=float)
        self.posts += 1
        if not np.all(np.isfinite(q)):
            self.violations.append(f"{self.link.name}: non-finite target {q}")
        elif not self._within_or_back(q, t):
            self.violations.append(f"{self.link.name}: target outside limits {q}")
        elif self.last is not None and 0 < t - self.last[1] <= 1.5 * self.period:
            speed = np.abs(q - self.last[0]) / (t - self.last[1])
            if np.any(speed > self.vmax * 1.0001 + 1e-9):
                i = int(np.argmax(speed / self.vmax))
                self.violations.append(f"{self.link.name}/{self.link.actuators[i]}: {speed[i]:.4g} > "
                                       f"{self.vmax[i]:.4g} SI/s")
        self.last = (q, t)
        self._post(targets, stamp)


    def _within_or_back(self, q: np.ndarray, t: float) -> bool:
        """Within the limits, or (an actuator found outside them when the head enabled) no further out than the
        previous cycle's target: the first target of a run of cycles starts where the actuator stands."""
        below, above = q < self.lo - 1e-9, q > self.hi + 1e-9
        if not (below.any() or above.any()):
            return True
        if self.last is None or not 0 < t - self.last[1] <= 1.5 * self.period:
            return True
        prev = self.last[0]
        return bool(np.all(~below | (q >= prev - 1e-12)) and np.all(~above | (q <= prev + 1e-12)))


def _rss(pid: int) -> int:
    """Resident memory of a process and its children, in bytes (Linux /proc)."""
    total = 0
    pids = [pid]
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            pids += [int(p) for p in fh.read().split()]
    except OSError:
        pass
    for p in pids:
        try:
            with open(f"/proc/{p}/status") as fh:
                for line in fh:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
        except OSError:
            pass
    return total


class Fuzzer:
    """Seeded request generator; each request is (frames, id to expect or None)."""

    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)
        self.n = 0

    def next_id(self) -> str:
        self.n += 1
        return f"fz{self.n}"

    def value(self, depth: int = 0) -> Any:
        r = self.rng
        kind = r.random()
        if depth > 3 or kind < 0.45:
            return r.choice([*NASTY, r.uniform(-1e3, 1e3), r.randint(-10, 10), r.choice(CHANNELS)])
        if kind < 0.7:
            return [self.value(depth + 1) for _ in range(r.randint(0, 4))]
        return {r.choice(["op", "id", "clip", "pose", "frames", "keys", r.choice(CHANNELS)]): self.value(depth + 1)
                for _ in range(r.randint(0, 4))}

    def op(self) -> str:
        op = self.rng.choice(OPS)
        while op in RARE_OPS and self.rng.random() < 0.8:
            op = self.rng.choice(OPS)
        return op

    def valid(self, op: str, rid: str) -> dict[str, Any]:
        r = self.rng
        now = time.monotonic()
        body: dict[str, Any] = {
            "hello": {"client": "fuzz"}, "clock": {"t_client": now}, "estop": {"reason": "fuzz"},
            "load_clip": {"clip": {"name": f"c{r.randint(0, 3)}", "channels": {
                "jaw": {"interp": r.choice(["step", "linear"]),
                        "keys": [[0.0, 0.0], [r.uniform(0.1, 1.0), r.uniform(-5, 40)]]},
                "brow_l": {"keys": [[0.0, r.uniform(-30, 30)], [0.5, r.uniform(-30, 30)]]}}}},
            "unload_clip": {"clip": f"c{r.randint(0, 3)}"},
            "play": {"clip": f"c{r.randint(0, 3)}", "speed": r.uniform(0.5, 2.0), "loop": r.random() < 0.5},
            "seek": {"time": r.uniform(0, 1)},
            "stream": {"channels": ["jaw", "brow_l"],
                       "frames": [[now + 0.02 * k, r.uniform(-10, 40), r.uniform(-40, 40)] for k in range(3)]},
            "pose": {"pose": {r.choice(["jaw", "brow_l", "blink", "cheek_r"]): r.uniform(-60, 60)},
                     "speed": r.uniform(0.05, 1.0)},
            "record": {"action": r.choice(["start", "stop"]), "name": "fuzz"},
        }.get(op, {})
        return {"op": op, "id": rid, **body}

    def mutate(self, msg: dict[str, Any]) -> tuple[dict[str, Any], bool]:
        """A mutated copy; the flag says whether its id is still readable."""
        r = self.rng
        msg = dict(msg)
        fields = [k for k in msg if k not in ("op", "id")]
        kind = r.randrange(7)
        if kind == 0 and fields:
            del msg[r.choice(fields)]
        elif kind == 1:
            msg[r.choice(["bogus", "speed", "at", "from", "loop", "time", "channels", "frames"])] = self.value()
        elif kind == 2 and fields:
            msg[r.choice(fields)] = self.value()
        elif kind == 3 and fields:  # one level down: a nested value retyped
            key = r.choice(fields)
            inner = msg[key]
            if isinstance(inner, dict) and inner:
                inner = dict(inner)
                inner[r.choice(list(inner))] = self.value()
                msg[key] = inner
            elif isinstance(inner, list) and inner:
                inner = list(inner)
                inner[r.randrange(len(inner))] = self.value()
                msg[key] = inner
        elif kind == 4:
            msg["op"] = r.choice(["", "dance", "STATUS", 7, None, "x" * 300, [msg["op"]]])
        elif kind == 5:
            msg["id"] = r.choice([1.5, None, [1], {"a": 1}, "i" * 200, True, b"id"])
            return msg, False
        else:
            for key in fields[:1] or ["pad"]:
                msg[key] = r.choice(NASTY)
        return msg, True

    def request(self) -> tuple[list[bytes], str | None]:
        r = self.rng
        rid = self.next_id()
        kind = r.random()
        if kind < 0.5:  # a mutated valid request of some op
            msg, keeps_id = self.mutate(self.valid(self.op(), rid))
            return [_pack(msg)], rid if keeps_id else None
        if kind < 0.62:  # a valid request
            return [_pack(self.valid(self.op(), rid))], rid
        if kind < 0.75:  # a random map with our id
            value = self.value()
            msg = value if isinstance(value, dict) else {"value": value}
            msg["id"] = rid
            return [_pack(msg)], rid
        if kind < 0.83:  # random bytes, a random non-map value, or a truncated request
            choice = r.randrange(3)
            if choice == 0:
                return [r.randbytes(r.randint(0, 64))], None
            if choice == 1:
                return [_pack([self.value()])], None
            raw = _pack(self.valid(self.op(), rid))
            return [raw[: r.randrange(1, len(raw))]], None
        if kind < 0.93:  # deep nesting, written by hand (msgpack's packer refuses it)
            depth = r.choice([40, 200, 1000])
            op = self.op()
            raw = (b"\x83" + _pack("op") + _pack(op) + _pack("id") + _pack(rid) + _pack(r.choice(["x", "pose", "clip"]))
                   + r.choice([b"\x91", b"\x81\xa1k"]) * depth + b"\xc0")
            return [raw], rid
        if kind < 0.97:  # oversize: more than max_message_bytes (1 MiB)
            return [_pack({"op": "status", "id": rid, "pad": b"x" * (MIB + r.randint(1, 4096))})], rid
        # multipart: refused as a whole, never echoed
        return [_pack({"op": "status", "id": rid}), _pack({"op": "hello"})], None


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _recover(c: Client) -> None:
    status = c.call("status")
    if status["lifecycle"] in ("estop", "fault"):
        c.request("reset", timeout=30)
        status = c.call("status")
    if status["lifecycle"] == "inactive":
        c.request("enable", timeout=30)


def test_fuzzed_requests_are_all_answered_within_limits_and_memory(make_daemon) -> None:
    print(f"\nfuzz seed {SEED} (LIKENESS_FUZZ_SEED={SEED} replays it)")
    try:
        _run(make_daemon, SEED)
    except AssertionError as exc:
        raise AssertionError(f"fuzz seed {SEED} (replay: LIKENESS_FUZZ_SEED={SEED}): {exc}") from None


def _run(make_daemon: Any, seed: int) -> None:
    t_start = time.monotonic()
    d = make_daemon()
    checks = [PostCheck(link, d.period) for link in d.buses]
    server_pid = d._server.pid
    fuzz = Fuzzer(seed)
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(d.command_endpoint)
    answered = anonymous = 0
    faults: list[str] = []
    configs = [motor_config(act) for act in d.head.actuators]  # what the drivers enforce, in driver units
    limits = {cfg.name: (cfg.min_position, cfg.max_position) for cfg in configs}
    with Client(d.command_endpoint, timeout=30) as c:
        for _ in range(3):  # a starved emulator on a loaded host may miss a heartbeat on the way up
            _recover(c)
            if c.call("status")["lifecycle"] == "active":
                break
        rss_start = _rss(server_pid)
        t_fuzz = time.monotonic()
        sent = batches = 0
        while sent < REQUESTS:
            expect: Counter[str] = Counter()
            unnamed = 0
            for _ in range(BATCH):
                frames, rid = fuzz.request()
                sock.send_multipart(frames)
                sent += 1
                if rid is None:
                    unnamed += 1
                else:
                    expect[rid] += 1
            deadline = time.monotonic() + 30.0
            while expect or unnamed:
                assert sock.poll(max(1, int(1000 * (deadline - time.monotonic())))), \
                    f"no reply within 30 s to {sorted(expect)[:5]} (+{unnamed} without a readable id)"
                reply = msgpack.unpackb(sock.recv(), raw=False, strict_map_key=False)
                assert isinstance(reply, dict) and "ok" in reply, reply
                rid = reply.get("id")
                if isinstance(rid, str) and expect.get(rid):
                    expect[rid] -= 1
                    if not expect[rid]:
                        del expect[rid]
                    answered += 1
                else:
                    assert reply["ok"] is False and reply["error"]["code"] in ERROR_CODES, reply
                    assert unnamed > 0, f"an unexpected reply: {str(reply)[:300]}"
                    unnamed -= 1
                    anonymous += 1
            status = c.call("status")
            if status["fault"] is not None:
                faults.append(status["fault"]["message"])
            truth = d.hw.simulated_positions()
            for name, q in truth.items():
                lo, hi = limits[name]
                margin = 0.02 * (hi - lo)
                assert lo - margin <= q <= hi + margin, f"{name} at {math.degrees(q):.2f} deg, outside its limits"
            batches += 1
            if batches % RECOVER_EVERY == 0:
                _recover(c)
        t_end = time.monotonic()
        rss_end = _rss(server_pid)
        c.request("record", action="stop")
        c.request("disable")
    sock.close()
    violations = [v for ch in checks for v in ch.violations]
    posts = sum(ch.posts for ch in checks)
    print(f"{sent} requests: {answered} answered by id, {anonymous} without a readable id; {posts} bus posts; "
          f"{len(faults)} batches ended in fault; API server RSS {rss_start / MIB:.0f} -> {rss_end / MIB:.0f} MiB; "
          f"start-up {t_fuzz - t_start:.1f} s, fuzzing {t_end - t_fuzz:.1f} s")
    assert not violations, violations[:5]
    assert not [f for f in faults if "CommandRejected" in f], faults  # a driver's own guard never had to refuse
    assert posts > 0
    assert rss_end - rss_start < RSS_GROWTH_BOUND, f"API server grew {(rss_end - rss_start) / MIB:.0f} MiB"


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-s"])
