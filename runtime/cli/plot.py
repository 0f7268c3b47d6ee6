"""``likeness plot``: a recording (``.lrec`` or ``.npz``) → PNG of commanded vs measured, with errors."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The recording and the PNG path."""
    p = parser
    p.add_argument("recording", type=Path, help="recording file (.lrec or .npz)")
    p.add_argument("-o", "--out", type=Path, default=None, help="PNG path (default: beside the recording)")


def run(args: argparse.Namespace) -> int:
    """Plot the recording and print its tracking errors."""
    from models.errors import UsageError
    from runtime.recording import load_recording, plot_recording, tracking_errors

    try:
        rec = load_recording(args.recording)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    out = args.out or args.recording.with_suffix(".png")
    plot_recording(rec, out, title=f"{args.recording.name}: commanded vs measured")
    print_errors(tracking_errors(rec))
    print(f"plot written: {out}")
    return 0


def print_errors(errors: dict[str, dict[str, float]]) -> None:
    """Table of per-actuator tracking error."""
    print(f"{'actuator':<20}{'rms error':>12}{'max error':>12}")
    for name, e in errors.items():
        print(f"{name:<20}{e['rms']:>10.3f} {e['unit']:<1}{e['max']:>10.3f} {e['unit']}")
