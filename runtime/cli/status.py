"""``likeness status``: print a running daemon's status (lifecycle, buses, loop, clip, actuators)."""

from __future__ import annotations

import argparse

from runtime.cli._client import add_client_options, connect


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The client options and --json."""
    add_client_options(parser)
    parser.add_argument("--json", action="store_true", help="print the raw reply as JSON")


def run(args: argparse.Namespace) -> int:
    """Ask for the status and print it."""
    import json

    with connect(args) as client:
        st = client.call("status")
    if args.json:
        print(json.dumps(st, indent=2, default=str))
        return 0
    print(f"lifecycle {st['lifecycle']}  mode {st['mode']}  buses " +
          ", ".join(f"{b}={s}" for b, s in st["buses"].items()))
    if st.get("estop"):
        print(f"e-stop latched: {st['estop']}")
    if st.get("fault"):
        print(f"fault: {st['fault'].get('source')}: {st['fault'].get('message')}")
    loop = st["loop"]
    print(f"loop {loop['rate_hz']:g} Hz, {loop['cycles']} cycles, {loop['missed']} missed; "
          f"jitter p99 {loop.get('jitter_p99_us', float('nan')):.1f} us; {st['realtime']}")
    tl = st["timeline"]
    if tl.get("clip"):
        print(f"clip {tl['clip']} at {tl['time'] or 0:.2f}/{tl['duration']:.2f} s"
              f"{' (paused)' if tl['paused'] else ''}{' (finished)' if tl['finished'] else ''}")
    ages = st.get("feedback_age_s") or {}
    if ages:
        print("feedback age " + "  ".join(f"{bus} {_ms(age)}" for bus, age in ages.items()))
    following = st.get("following_error") or {}
    print(f"{'actuator':<20}{'commanded':>12}{'measured':>12}{'peak error':>12}")
    for name, cmd in st["commanded"].items():
        meas = st["measured"].get(name)
        print(f"{name:<20}{_fmt(cmd):>12}{_fmt(meas):>12}{_fmt(following.get(name)):>12}")
    return 0


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _ms(age: float | None) -> str:
    """A feedback age as milliseconds ("-" before the first report)."""
    return "-" if age is None or age != age or age == float("inf") else f"{age * 1e3:.0f} ms"
