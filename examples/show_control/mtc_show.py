"""A show under timecode: load a performance, then play MIDI timecode over mido's TCP MIDI port; the head chases.

Run a daemon with the timecode input first:
    likeness daemon --config heads/sample/head.toml --inputs examples/show_control/timecode.toml
    python examples/show_control/mtc_show.py [--command tcp://127.0.0.1:5555] [--mtc 127.0.0.1:5004]

It loads ``heads/sample/performances/expressive.json`` (chased at 01:00:00:00 in the config) and enables the head
over the ZeroMQ protocol, then, as a timecode master: rolls from 01:00:00:00, drops out for two seconds (the head
freewheels, then holds), and jumps to 01:00:05:00 (the clip relocates). It prints the clock status as it goes.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mido.sockets

from models.client import Client
from models.clip import clip_file_as_dict
from runtime.inputs.mtcgen import MtcGenerator

ROOT = Path(__file__).resolve().parents[2]
HOUR = 3600.0


def clock(c: Client, what: str) -> dict:
    s = c.call("status")
    k, tl = s.get("clock") or {}, s.get("timeline") or {}
    print(f"{what:>10}: timecode {k.get('timecode')} ({k.get('state')}, {k.get('rate')} fps); source {s['source']}, "
          f"clip {tl.get('clip')} at {tl.get('time') or 0:.2f} s; jaw {s['commanded']['jaw']:.1f} deg", flush=True)
    return s


def wait_for(c: Client, states: tuple[str, ...], timeout: float = 15.0) -> None:
    """Until the chase is in one of ``states`` (a busy host may take a moment to lock)."""
    end = time.monotonic() + timeout
    while c.call("status")["clock"]["state"] not in states and time.monotonic() < end:
        time.sleep(0.1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--command", default="tcp://127.0.0.1:5555", help="the daemon's command endpoint")
    parser.add_argument("--mtc", default="127.0.0.1:5004", help="the daemon's [inputs.timecode] bind")
    parser.add_argument("--clip", type=Path, default=ROOT / "heads" / "sample" / "performances" / "expressive.json")
    parser.add_argument("--rate", default="25")
    parser.add_argument("--roll", type=float, default=3.0, help="seconds of timecode before the dropout")
    args = parser.parse_args(argv)

    host, port = args.mtc.rsplit(":", 1)
    with Client(args.command, timeout=30) as c:
        c.call("load_clip", clip=clip_file_as_dict(args.clip))
        if c.call("status")["lifecycle"] != "active":
            c.call("enable")
        gen = MtcGenerator(mido.sockets.connect(host, int(port)), args.rate)
        try:
            gen.roll(HOUR)
            wait_for(c, ("locked",))
            time.sleep(args.roll)
            clock(c, "rolling")
            gen.halt()  # dropout
            time.sleep(0.5)
            clock(c, "dropout")
            wait_for(c, ("hold",))
            clock(c, "held")
            gen.roll(HOUR + 5.0)  # comes back elsewhere: the clip relocates
            wait_for(c, ("locked",))
            time.sleep(1.0)
            clock(c, "relocated")
            gen.halt()
        finally:
            gen.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
