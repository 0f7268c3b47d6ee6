"""``likeness sim tracker``: serve the simulated marker tracker of the sample head as a ZeroMQ capture stream.

The mechanism follows the actuator positions a running daemon measures (its ``status`` op), so
``likeness calibrate --daemon ... --tracker zmq://...`` can calibrate the emulated head across processes,
exactly as it would with a real capture system (format: ``docs/tracker.md``). With ``--stdin`` it follows
positions written to its standard input instead (ideal motors: ``likeness calibrate --ideal-motors``): one JSON map
of SI actuator values per line, each answered with the line ``ok`` once every frame published shows it.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from models.headspec import HeadSpec
    from sim_hardware.tracker import TrackerPublisher


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The head, what to follow (a daemon or stdin), the PUB endpoint and the tracker's noise."""
    p = parser
    p.add_argument("--config", required=True, type=Path, help="head config TOML (the sample head)")
    p.add_argument("--daemon", default="tcp://127.0.0.1:5555", help="daemon command endpoint to follow")
    p.add_argument("--stdin", action="store_true",
                   help="follow SI actuator values read from stdin (a JSON map per line, answered 'ok') instead")
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

    from models.errors import UsageError
    from models.headspec import load_head
    from sim_hardware.mechanism import sample_mechanism
    from sim_hardware.tracker import SimTracker, TrackerNoise, TrackerPublisher

    head = load_head(args.config)
    mech = sample_mechanism(head)
    if set(mech.actuators) != set(head.actuator_names):
        raise UsageError(f"the simulated mechanism is the sample head's; {args.config} has other actuators")
    last: dict[str, float] = {a.name: a.neutral for a in head.actuators}
    positions = (lambda: dict(last)) if args.stdin else _DaemonPositions(args.daemon, head, last)
    noise = TrackerNoise(position_sigma=args.noise_mm * 1e-3, rotation_sigma=math.radians(args.noise_deg),
                         dropout_rate=args.dropout, outlier_rate=args.outliers)
    tracker = SimTracker(mech, positions, noise=noise, rate_hz=args.rate, seed=args.seed, realtime=True)
    pub = TrackerPublisher(tracker, args.bind)
    following = "stdin" if args.stdin else args.daemon
    print(f"tracker: publishing {len(mech.links)} links at {args.rate:g} Hz on {pub.endpoint} "
          f"(following {following})", flush=True)
    try:
        if args.stdin:
            _follow_stdin(pub, last)
        else:
            end = time.monotonic() + args.duration if args.duration > 0 else math.inf
            while time.monotonic() < end:
                time.sleep(min(0.2, max(end - time.monotonic(), 0.0)))
    except KeyboardInterrupt:
        pass
    finally:
        pub.close()
        close = getattr(positions, "close", None)
        if close is not None:
            close()
    return 0


class _DaemonPositions:
    """The daemon's measured actuator positions (SI) through its ``status`` op; the last known on no answer."""

    def __init__(self, endpoint: str, head: HeadSpec, last: dict[str, float]) -> None:
        import zmq

        # the daemon's protocol (docs/protocol.md) spoken directly: a DEALER socket, msgpack maps
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.head = head
        self.last = last
        self.ids = iter(range(1, 1 << 62))

    def __call__(self) -> dict[str, float]:
        import time

        import msgpack

        rid = next(self.ids)
        self.sock.send(msgpack.packb({"op": "status", "id": rid}, use_bin_type=True))
        measured = {}
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            if not self.sock.poll(50):
                continue
            reply = msgpack.unpackb(self.sock.recv(), raw=False)
            if isinstance(reply, dict) and reply.get("id") == rid:
                measured = (reply.get("measured") or {}) if reply.get("ok") else {}
                break
        for name, value in measured.items():  # no answer: keep the last known pose
            if value is not None and name in self.last:
                self.last[name] = self.head.actuator(name).from_config_units(float(value))
        return dict(self.last)

    def close(self) -> None:
        self.sock.close(0)


def _follow_stdin(pub: TrackerPublisher, last: dict[str, float]) -> None:
    """Take each line of stdin as the new SI positions; answer ``ok`` once two frames were published after it
    (the frame being captured when the line arrived may still show the old ones)."""
    import json
    import sys
    import time

    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            values = json.loads(line)
            update = {str(k): float(v) for k, v in values.items() if k in last}
        except (ValueError, TypeError, AttributeError) as exc:
            print(f"error: {exc}", flush=True)
            continue
        last.update(update)
        seen = pub.frames
        while pub.frames < seen + 2:
            time.sleep(0.001)
        print("ok", flush=True)
