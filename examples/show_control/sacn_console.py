"""A console driving the head over sACN (E1.31) with the ``sacn`` library's sender, as a lighting desk would.

Run a daemon with the sACN input first, enable the head (``likeness enable``), then:
    likeness daemon --config heads/sample/head.toml --inputs examples/show_control/console_sacn.toml
    python examples/show_control/sacn_console.py [--dest 127.0.0.1] [--universe 1] [--priority 100]

It fades the jaw open and closed (16-bit, slots 1-2), blinks (slot 3) and raises the brows (slots 4-5) for a few
seconds at 40 frames per second, then stops sending: after the data-loss time the daemon's watchdog holds the head
and eases it to neutral, as for a lost stream.
"""

from __future__ import annotations

import argparse
import math
import time

import sacn


def frame(t: float, jaw_max: float = 28.0, jaw_min: float = -2.0) -> tuple[int, ...]:
    """The universe at ``t`` seconds into the cue (slot 1 is index 0)."""
    jaw = 12.0 * math.sin(math.pi * min(t / 2.0, 1.0))  # degrees
    raw = round((jaw - jaw_min) / (jaw_max - jaw_min) * 65535)
    blink = 255 if 1.0 < t % 2.0 < 1.15 else 0
    brow = round((8.0 * math.sin(math.pi * min(t / 3.0, 1.0)) + 10.0) / 35.0 * 255)
    data = [0] * 512
    data[0], data[1], data[2], data[3], data[4] = raw >> 8, raw & 0xFF, blink, brow, brow
    return tuple(data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dest", default="127.0.0.1", help="the daemon's [inputs.sacn] bind address (unicast)")
    parser.add_argument("--universe", type=int, default=1)
    parser.add_argument("--priority", type=int, default=100)
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args(argv)

    sender = sacn.sACNsender(bind_address="127.0.0.1", bind_port=0, source_name="likeness example console",
                             universeDiscovery=False, fps=40)
    sender.start()
    sender.activate_output(args.universe)
    out = sender[args.universe]
    out.multicast = False
    out.destination = args.dest
    out.priority = args.priority
    try:
        start = time.monotonic()
        while (t := time.monotonic() - start) < args.seconds:
            out.dmx_data = frame(t)
            time.sleep(1 / 40)
    finally:
        sender.stop()  # silence: the daemon's watchdog takes over after the data-loss time
    print(f"sent {args.seconds:g} s of universe {args.universe} to {args.dest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
