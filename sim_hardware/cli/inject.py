"""``likeness sim inject``: send one fault-injection request to a running emulator's control endpoint.

Works with any emulator that serves :class:`models.emulator_control.ControlServer`; parameters are
``key=value`` pairs, with values read as integers (``0x`` hex allowed), floats, ``true``/``false``
or strings. Example: ``likeness sim inject --control tcp://127.0.0.1:5600 drive_fault device=3 code=0x2310``.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any


def parse_value(text: str) -> int | float | bool | str:
    """``"0x10"`` → 16, ``"1.5"`` → 1.5, ``"true"`` → True, anything else stays a string."""
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def parse_params(pairs: list[str]) -> dict[str, Any]:
    """``["device=3", "code=0x2310"]`` → ``{"device": 3, "code": 0x2310}`` (UsageError naming a bad pair)."""
    from models.errors import UsageError

    params: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key or key in ("op", "fault"):
            raise UsageError(f"parameter {pair!r}: expected key=value (key not 'op' or 'fault')")
        params[key] = parse_value(value)
    return params


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The control endpoint, the fault and its parameters."""
    parser.description = __doc__
    parser.add_argument("--control", required=True, metavar="ENDPOINT", help="emulator control endpoint (ZeroMQ)")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the answer (default 2)")
    parser.add_argument("fault", help="fault name, e.g. stop_heartbeat, drive_fault, freeze_feedback, slip, frames, "
                        "clear, status (docs/operations.md lists each emulator's faults)")
    parser.add_argument("params", nargs="*", metavar="KEY=VALUE", help="fault parameters")


def run(args: argparse.Namespace) -> int:
    """Send the request, print the reply as JSON; exit 0 when the emulator accepted it, 1 otherwise."""
    from models.errors import UsageError

    message = {"op": "inject", "fault": args.fault, **parse_params(args.params)}
    from models.emulator_control import request

    try:
        reply = request(args.control, message, timeout_s=args.timeout)
    except TimeoutError as exc:
        raise UsageError(str(exc)) from exc
    print(json.dumps(reply, sort_keys=True, default=str))
    if not reply.get("ok", False):
        print(f"likeness sim inject: emulator refused: {reply.get('error', 'unknown error')}", file=sys.stderr)
        return 1
    return 0
