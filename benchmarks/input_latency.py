"""Show-control input latency: a packet sent by the input's own library (python-osc, sacn, mido) to the bus write
that carries its value (the bus process's write time), p50/p99 per input, at the head's loop rate, beside the
ZeroMQ stream's frame sent → bus write measured in the same run (goal: p99 <= 2 ms, as for the ZeroMQ stream).

Per trial: wait for the jaw to stand still, send one packet that moves it (OSC ``/face/jaw``; an sACN universe
flushed by the sender; an MTC full-frame locate of a chased ramp clip; a ZeroMQ ``stream`` frame stamped now, with
the jitter buffer's delay at 1 ms), and poll the CAN bus link's last write until the jaw target changes. Includes
the wait for the next control cycle (up to one period). A stream frame that reaches the daemon after its play-out
time is late and moves nothing: such trials are left out of the stream's figures, as a lost packet is for any input.
Then the goal's case for a live input: an OSC sender and an sACN sender, each in a process of its own, sending a
value every loop period on a fixed grid (the jaw stepping between 0° and 4° every 125–175 packets), to a daemon with
``[runtime] stream_phase_lock = true``; the figure is a step packet's send time → the first bus write that moved
the jaw. Run with nothing else on the machine:
``python benchmarks/input_latency.py [--trials 100] [--rate 250] [--steps 40]``.
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zmq

try:
    from benchmarks import _daemon as D
except ImportError:  # run as a script
    import _daemon as D

FRAGMENT = """
[inputs.osc]
bind = "127.0.0.1:0"
watchdog = false
[inputs.osc.map]
"/face/jaw" = "jaw"

[inputs.sacn]
bind = "{sacn}"
universe = 1
[[inputs.sacn.slots]]
channel = "jaw"
bits = 16
range = [0.0, 20.0]

[inputs.timecode]
bind = "127.0.0.1:0"
rate = "25"
lock_samples = 1
[inputs.timecode.clips]
ramp = "00:00:10:00"
"""
RAMP = {"name": "ramp", "channels": {"jaw": {"interp": "linear", "keys": [[0, 0], [20, 20]]}}}


def start_daemon(rate: float, tmp: Path, phase_lock: bool = False, extra: dict[str, Any] | None = None) -> Any:
    from models.headspec import load_head
    from runtime.daemon import Daemon

    sacn_ip = f"127.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
    head = load_head(D.patient_head(tmp / "head" / "head.toml", FRAGMENT.replace("{sacn}", sacn_ip)))
    overrides = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                 "runtime.rate_hz": rate, "runtime.telemetry_hz": min(50, rate), "runtime.stream_delay_s": 0.001,
                 "safety.feedback_timeout_s": 0.5, "safety.watchdog_hold_s": 5.0, "safety.watchdog_neutral_s": 10.0,
                 "runtime.stream_phase_lock": phase_lock, **(extra or {})}
    daemon = Daemon(head, overrides, target_solvers=())
    daemon.start()
    ready(daemon)
    return daemon


def ready(daemon: Any) -> None:
    """The head active (a bus fault an emulator caused earlier is reset first)."""
    for _ in range(3):
        s = daemon.call("status")
        if s["lifecycle"] == "active":
            return
        if s["lifecycle"] in ("fault", "estop") or "fault" in s["buses"].values():
            daemon.call("reset")
        try:
            daemon.call("enable")
        except Exception as exc:  # the next try resets it
            print(f"(enable failed: {exc})")


def measure(daemon: Any, trials: int, send: Callable[[float], None]) -> list[float]:
    """Latencies (s) of ``send(jaw_degrees)`` → the first bus write whose jaw target moved."""
    link = next(lk for lk in daemon.buses if "jaw" in lk.actuators)
    j = link.actuators.index("jaw")
    lat: list[float] = []
    rng = np.random.default_rng(1)
    ready(daemon)
    for _ in range(trials):
        if daemon.lifecycle != "active":
            ready(daemon)
        time.sleep(rng.uniform(0, daemon.period))  # a random phase in the cycle
        settle = time.monotonic() + 1.0
        while np.any(np.abs(daemon.state.shaper.v) > 1e-9) and time.monotonic() < settle:
            time.sleep(0.002)
        fb = link.feedback()
        before, stamp0 = float(fb.written[j]), fb.write_stamp
        value = 6.0 if np.degrees(before) < 4.0 else 2.0  # always a move away from where it is
        t_send = time.monotonic()
        send(value)
        end = t_send + 0.5
        while time.monotonic() < end:
            fb = link.feedback()
            if fb.write_stamp > stamp0 and abs(float(fb.written[j]) - before) > 1e-9:
                lat.append(fb.write_stamp - t_send)
                break
            time.sleep(0.0001)
    return lat


def _steady_sender(kind: str, target: str, rate: float, steps: int, seed: int, out: Any) -> None:
    """A live sender in a process of its own: one packet per period on a fixed grid (``kind`` "osc" to host:port
    ``target``, "sacn" unicast to IP ``target``), the jaw stepping between 0° and 4° every 125–175 packets; puts
    the send times of the step packets on ``out``. It runs as a sender on a machine of its own would
    (:func:`external_sender`)."""
    D.external_sender()
    rng = np.random.default_rng(seed)
    if kind == "osc":
        from pythonosc.udp_client import SimpleUDPClient

        host, port = target.rsplit(":", 1)
        osc = SimpleUDPClient(host, int(port))

        def send(v: float) -> None:
            osc.send_message("/face/jaw", v)
        stop: Callable[[], None] = lambda: None  # noqa: E731
    else:
        import sacn

        sender = sacn.sACNsender(bind_address="127.0.0.1", bind_port=0, universeDiscovery=False, fps=40)
        sender.manual_flush = True
        sender.start()
        sender.activate_output(1)
        sender[1].multicast = False
        sender[1].destination = target

        def send(v: float) -> None:
            raw = round(v / 20.0 * 65535)
            sender[1].dmx_data = (raw >> 8, raw & 0xFF)
            sender.flush()
        stop = sender.stop
    period = 1.0 / rate
    sent: list[float] = []
    value, k, next_step = 0.0, 0, int(rng.integers(125, 175))
    t_next = time.monotonic() + period
    give_up = time.monotonic() + 30.0 + 2.0 * steps
    while len(sent) < steps and time.monotonic() < give_up:
        D.sleep_until(t_next)
        t_next += period
        k += 1
        step = k == next_step
        if step:
            value = 4.0 if value == 0.0 else 0.0
            next_step = k + int(rng.integers(125, 175))
        t_send = time.monotonic()
        send(value)
        if step:
            sent.append(t_send)
    stop()
    out.put(sent)


def steady(daemon: Any, kind: str, target: str, rate: float, steps: int) -> tuple[list[float], Any]:
    """Step packets of a steady sender (:func:`_steady_sender`) → the first bus write that moved the jaw (s), and
    the phase lock's state at the end (``status`` → ``loop.stream_phase_lock``)."""
    stamps, values, sent = D.run_sender_watching_jaw(daemon, _steady_sender, (kind, target, rate, steps, 3),
                                                     f"{kind} sender")
    lock = daemon.call("status").get("loop", {}).get("stream_phase_lock")
    lat = D.first_moves(stamps, values, sent)
    return lat, lock


def main(argv: list[str] | None = None) -> int:
    import mido.sockets
    import sacn
    from pythonosc.udp_client import SimpleUDPClient

    from models.client import Client
    from runtime.inputs.mtc import frame_of, full_frame

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--rate", type=float, default=250.0)
    parser.add_argument("--steps", type=int, default=40, help="timed steps per steady sender (0: skip)")
    D.add_emulator_nice(parser)
    D.add_settings(parser)
    args = parser.parse_args(argv)
    extra = D.settings(args)
    emulators = D.demote_emulators(args.emulator_nice)
    results: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        daemon = start_daemon(args.rate, Path(tmp), extra=extra)
        try:
            with Client(daemon.command_endpoint) as c:
                hello = c.call("hello")
                offset, _ = c.clock_offset()
                c.call("load_clip", clip=RAMP)
            inputs = hello["inputs"]

            # ZeroMQ stream (the baseline): a raw DEALER, timed from the send
            sock = zmq.Context.instance().socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(daemon.command_endpoint)

            def zmq_send(v: float) -> None:
                sock.send(msgpack.packb({"op": "stream", "channels": ["jaw"],
                                         "frames": [[time.monotonic() + offset, v]]}))

            results["zeromq stream"] = measure(daemon, args.trials, zmq_send)
            while sock.poll(0):
                sock.recv()
            sock.close(0)

            host, port = inputs["osc"]["udp"].rsplit(":", 1)
            osc = SimpleUDPClient(host, int(port))
            results["osc"] = measure(daemon, args.trials, lambda v: osc.send_message("/face/jaw", v))

            sender = sacn.sACNsender(bind_address="127.0.0.1", bind_port=0, universeDiscovery=False, fps=40)
            sender.manual_flush = True  # the packet leaves when flush() is called, in this thread
            sender.start()
            sender.activate_output(1)
            sender[1].multicast = False
            sender[1].destination = inputs["sacn"]["bind"].rsplit(":", 1)[0]

            def sacn_send(v: float) -> None:
                raw = round(v / 20.0 * 65535)
                sender[1].dmx_data = (raw >> 8, raw & 0xFF)
                sender.flush()

            results["sacn"] = measure(daemon, args.trials, sacn_send)
            sender.stop()

            host, port = inputs["timecode"]["bind"].rsplit(":", 1)
            mtc = mido.sockets.connect(host, int(port))
            # a locate into the chased ramp clip (00:00:10:00 + v seconds puts the jaw at v degrees)
            results["mtc locate"] = measure(daemon, args.trials,
                                            lambda v: mtc.send(full_frame(frame_of(10.0 + v, "25"), "25")))
            mtc.close()
            state = daemon.lifecycle
        finally:
            daemon.stop()
        steady_results: dict[str, tuple[list[float], Any]] = {}
        if args.steps > 0:
            daemon = start_daemon(args.rate, Path(tmp) / "locked", phase_lock=True, extra=extra)
            try:
                inputs = daemon.call("hello")["inputs"]
                time.sleep(0.5)
                steady_results["osc"] = steady(daemon, "osc", inputs["osc"]["udp"], args.rate, args.steps)
                ready(daemon)
                sacn_ip = inputs["sacn"]["bind"].rsplit(":", 1)[0]
                steady_results["sacn"] = steady(daemon, "sacn", sacn_ip, args.rate, args.steps)
            finally:
                daemon.stop()
    period = 1e6 / args.rate
    base = results["zeromq stream"]
    b50, b99 = D.pct(base, 50) * 1e6, D.pct(base, 99) * 1e6
    print(f"{emulators}; settings {extra or 'default'}; load average {os.getloadavg()[0]:.1f} at the end")
    print(f"packet sent -> bus write at {args.rate:g} Hz (loop period {period:.0f} us; goal p99 <= 2000 us) [{state}]")
    for name, lat in results.items():
        l50, l99 = D.pct(lat, 50) * 1e6, D.pct(lat, 99) * 1e6
        ratio = "" if name == "zeromq stream" else f"  (x{l50 / b50:.2f} / x{l99 / b99:.2f} the ZeroMQ stream)"
        print(f"  {name:14s} {len(lat):4d}/{args.trials} trials: p50 {l50:6.0f} us, p99 {l99:6.0f} us{ratio}")
    if steady_results:
        print(f"steady senders at {args.rate:g} Hz, phase lock on, step packet sent -> bus write "
              "(goal p99 <= 2000 us):")
        for name, (lat, lock) in steady_results.items():
            l50, l99 = D.pct(lat, 50) * 1e6, D.pct(lat, 99) * 1e6
            print(f"  {name:14s} {len(lat):4d}/{args.steps} steps:  p50 {l50:6.0f} us, p99 {l99:6.0f} us  "
                  f"(x{l50 / b50:.2f} / x{l99 / b99:.2f} the single ZeroMQ frames); phase lock at the end: {lock}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
