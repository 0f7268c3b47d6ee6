"""A minimal show-control client of the Likeness daemon: pyzmq and msgpack only, following docs/protocol.md.

It says hello, enables the head, loads and plays a one-second nod of the jaw, streams half a second of brow frames
timestamped on the daemon clock, watches telemetry, and leaves the head disabled. Run a daemon first
(``likeness daemon``), then ``python examples/minimal_client.py [tcp://127.0.0.1:5555]``.
"""

from __future__ import annotations

import sys
import time

import msgpack
import zmq


class Daemon:
    """Request/reply over a DEALER socket."""

    def __init__(self, endpoint: str) -> None:
        self.sock = zmq.Context.instance().socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.next_id = 0

    def __call__(self, op: str, **fields: object) -> dict:
        self.next_id += 1
        self.sock.send(msgpack.packb({"op": op, "id": self.next_id, **fields}))
        if not self.sock.poll(5000):
            raise TimeoutError(f"{op}: no reply")
        reply = msgpack.unpackb(self.sock.recv())
        if not reply["ok"]:
            raise RuntimeError(f"{op}: {reply['error']['code']}: {reply['error']['message']}")
        return reply


def main(endpoint: str = "tcp://127.0.0.1:5555") -> int:
    daemon = Daemon(endpoint)
    hello = daemon("hello", client="minimal_client")
    print(f"protocol {hello['protocol']}, head {hello['head']['name']!r}, "
          f"{len(hello['head']['actuators'])} actuators at {hello['rate_hz']} Hz")

    telemetry = zmq.Context.instance().socket(zmq.SUB)
    telemetry.setsockopt(zmq.LINGER, 0)
    telemetry.setsockopt(zmq.SUBSCRIBE, b"")
    telemetry.connect(hello["telemetry"])

    if daemon("status")["lifecycle"] != "active":
        daemon("enable")

    # A clip in the jaw's configured unit (degrees): open, close.
    daemon("load_clip", clip={"name": "nod", "channels": {"jaw": {"interp": "linear",
                                                                 "keys": [[0, 0], [0.5, 12], [1.0, 0]]}}})
    daemon("play", clip="nod")
    time.sleep(1.2)

    # Streamed frames on the daemon clock: estimate the offset, then send 50 frames 10 ms apart.
    t0 = time.monotonic()
    clock = daemon("clock")
    offset = 0.5 * ((clock["t_recv"] - t0) + (clock["t_send"] - time.monotonic()))
    start = time.monotonic() + offset
    late = 0
    for k in range(50):
        frame = [start + 0.01 * k, 10.0 * k / 49]  # brow_l up to 10 degrees
        late += daemon("stream", channels=["brow_l"], frames=[frame])["late"]
        time.sleep(0.01)
    print(f"streamed 50 frames, {late} late")

    seen = 0
    end = time.monotonic() + 0.5
    while time.monotonic() < end and telemetry.poll(100):
        topic, payload = telemetry.recv_multipart()
        msg = msgpack.unpackb(payload)
        if topic == b"state":
            seen += 1
            last = msg
    if seen:
        print(f"telemetry: {seen} state messages; brow_l commanded {last['commanded']['brow_l']:.2f}, "
              f"measured {last['measured']['brow_l']:.2f} deg")
    status = daemon("status")
    print(f"lifecycle {status['lifecycle']}, loop missed {status['loop']['missed']} of {status['loop']['cycles']}")
    daemon("disable")
    telemetry.close()
    daemon.sock.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:2]))
