"""``likeness sim tracker``: serve the simulated marker tracker of the sample head as a ZeroMQ capture stream.

The mechanism follows the actuator positions a running daemon measures (its ``status`` op), so
``likeness calibrate --daemon ... --tracker zmq://...`` can calibrate the emulated head across processes,
exactly as it would with a real capture system (format: ``docs/tracker.md``).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The head, the daemon to follow, the PUB endpoint and the tracker's noise."""
    p = parser
    p.add_argument("--config", required=True, type=Path, help="head config TOML (the sample head)")
    p.add_argument("--daemon", default="tcp://127.0.0.1:5555", help="daemon command endpoint to follow")
    p.add_argument("--bind", default="tcp://127.0.0.1:7000", help="PUB endpoint (default tcp://127.0.0.1:7000)")
    p.add_argument("--rate", type=float, default=120.0, help="frames per second (default 120)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise-mm", type=float, default=0.2)
    p.add_argument("--noise-deg", type=float, default=0.2)
    p.add_argument("--dropout", type=float, default=0.02)
    p.add_argument("--outliers", type=float, default=0.01)
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    """Publish until interrupted."""
    import math
    import time

    import msgpack
    import zmq

    from models.errors import UsageError
    from models.headspec import load_head
    from sim_hardware.mechanism import sample_mechanism
    from sim_hardware.tracker import SimTracker, TrackerNoise, TrackerPublisher

    head = load_head(args.config)
    mech = sample_mechanism(head)
    if set(mech.actuators) != set(head.actuator_names):
        raise UsageError(f"the simulated mechanism is the sample head's; {args.config} has other actuators")
    # the daemon's protocol (docs/protocol.md) spoken directly: a DEALER socket, msgpack maps
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(args.daemon)
    last: dict[str, float] = {a.name: a.neutral for a in head.actuators}
    ids = iter(range(1, 1 << 62))

    def positions() -> dict[str, float]:
        rid = next(ids)
        sock.send(msgpack.packb({"op": "status", "id": rid}, use_bin_type=True))
        measured = {}
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            if not sock.poll(50):
                continue
            reply = msgpack.unpackb(sock.recv(), raw=False)
            if isinstance(reply, dict) and reply.get("id") == rid:
                measured = (reply.get("measured") or {}) if reply.get("ok") else {}
                break
        for name, value in measured.items():  # no answer: keep the last known pose
            if value is not None and name in last:
                last[name] = head.actuator(name).from_config_units(float(value))
        return dict(last)

    noise = TrackerNoise(position_sigma=args.noise_mm * 1e-3, rotation_sigma=math.radians(args.noise_deg),
                         dropout_rate=args.dropout, outlier_rate=args.outliers)
    tracker = SimTracker(mech, positions, noise=noise, rate_hz=args.rate, seed=args.seed, realtime=True)
    pub = TrackerPublisher(tracker, args.bind)
    print(f"tracker: publishing {len(mech.links)} links at {args.rate:g} Hz on {pub.endpoint} "
          f"(following {args.daemon})", flush=True)
    try:
        end = time.monotonic() + args.duration if args.duration > 0 else math.inf
        while time.monotonic() < end:
            time.sleep(min(0.2, max(end - time.monotonic(), 0.0)))
    except KeyboardInterrupt:
        pass
    finally:
        pub.close()
        sock.close(0)
    return 0
