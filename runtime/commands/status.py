"""``likeness status`` / ``estop`` / ``reset`` / ``enable`` / ``disable``: one request each to a running daemon."""

from __future__ import annotations

import argparse

from runtime.commands._common import add_client_options, call, connect


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="print the daemon's status")
    add_client_options(p)
    p.add_argument("--json", action="store_true", help="print the raw reply as JSON")
    p.set_defaults(func=run_status)
    p = sub.add_parser("estop", help="latch the daemon's e-stop (motion stops, torque off as configured)")
    add_client_options(p)
    p.add_argument("--reason", default="likeness estop", help="reason recorded with the e-stop")
    p.set_defaults(func=run_estop)
    for name, text in (("reset", "clear a latched e-stop or fault (head returns to inactive, torque off)"),
                       ("enable", "torque on: the head starts following commands"),
                       ("disable", "torque off")):
        p = sub.add_parser(name, help=text)
        add_client_options(p)
        p.set_defaults(func=run_simple, op=name)


def run_status(args: argparse.Namespace) -> int:
    import json

    with connect(args) as client:
        st = call(client, "status")
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
    print(f"{'actuator':<20}{'commanded':>12}{'measured':>12}")
    for name, cmd in st["commanded"].items():
        meas = st["measured"].get(name)
        print(f"{name:<20}{_fmt(cmd):>12}{_fmt(meas):>12}")
    return 0


def _fmt(x: object) -> str:
    return "-" if x is None else f"{x:.3f}"


def run_estop(args: argparse.Namespace) -> int:
    with connect(args) as client:
        reply = call(client, "estop", reason=args.reason)
    print(f"e-stop latched; lifecycle {reply['lifecycle']} (send 'likeness reset' to clear)")
    return 0


def run_simple(args: argparse.Namespace) -> int:
    with connect(args) as client:
        reply = call(client, args.op)
    print(f"{args.op}: lifecycle {reply['lifecycle']}")
    return 0
