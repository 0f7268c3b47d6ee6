"""A cue system driving the head over OSC (python-osc only), as QLab or TouchDesigner would.

Run a daemon with the OSC input first:
    likeness daemon --config heads/sample/head.toml --inputs examples/show_control/cue_osc.toml
then: python examples/show_control/osc_cue_system.py [--host 127.0.0.1] [--port 9000]

It enables the head (a control address: the daemon allows it for senders on control_allow), plays a two-second cue
by streaming the jaw and the brows at 50 Hz (the brows in one bundle, so they change in the same control cycle),
and disables the head. OSC is one-way: watch ``likeness status`` or telemetry to see the head follow.
"""

from __future__ import annotations

import argparse
import math
import time

from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.udp_client import SimpleUDPClient


def brows(value: float) -> OscBundle:
    """One bundle setting both brows: applied atomically."""
    bundle = OscBundleBuilder(IMMEDIATELY)
    for side in ("l", "r"):
        msg = OscMessageBuilder(f"/face/brow/{side}")
        msg.add_arg(float(value))
        bundle.add_content(msg.build())
    return bundle.build()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=9000)
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the cue")
    parser.add_argument("--wait", type=float, default=3.0, help="seconds to wait after enabling")
    parser.add_argument("--keep-enabled", action="store_true", help="do not disable the head at the end")
    args = parser.parse_args(argv)

    osc = SimpleUDPClient(args.host, args.port)
    osc.send_message("/likeness/enable", [])
    time.sleep(args.wait)  # the buses enable torque
    start = time.monotonic()
    while (t := time.monotonic() - start) < args.seconds:
        phase = t / args.seconds
        osc.send_message("/face/jaw", 10.0 * math.sin(math.pi * phase))  # degrees, the channel's unit
        osc.send(brows(6.0 * math.sin(math.pi * min(1.0, 2 * phase))))
        time.sleep(0.02)
    osc.send_message("/face/jaw", 0.0)
    osc.send(brows(0.0))
    time.sleep(1.0)
    if not args.keep_enabled:
        osc.send_message("/likeness/disable", [])
    print(f"cue sent to {args.host}:{args.port}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
