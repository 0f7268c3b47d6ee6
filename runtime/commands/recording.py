"""``likeness recording list|info|replay``: what the daemon recorded, and playing its commanded curves again."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from runtime.commands._common import add_client_options, call, connect

#: Keys sent by ``replay`` at most (all channels together): keeps the ``load_clip`` request under 1 MiB.
REPLAY_MAX_KEYS = 40_000
SUFFIXES = (".lrec", ".npz")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recording", help="list, inspect and replay recordings (.lrec, .npz)")
    rsub = p.add_subparsers(dest="recording_command", metavar="ACTION")
    ls = rsub.add_parser("list", help="recordings in a folder with frame count and time span")
    ls.add_argument("dir", type=Path, nargs="?", default=Path("recordings"),
                    help="folder (default: ./recordings, the daemon's default [runtime] record_dir)")
    ls.set_defaults(func=run_list)
    info = rsub.add_parser("info", help="frame count, time span and channels of one recording")
    info.add_argument("file", type=Path)
    info.set_defaults(func=run_info)
    rp = rsub.add_parser("replay", help="send a recording's commanded curves to a daemon as a clip and play it")
    rp.add_argument("file", type=Path)
    add_client_options(rp)
    rp.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    rp.add_argument("--enable", action="store_true", help="enable torque first if the head is inactive")
    rp.add_argument("--max-keys", type=int, default=REPLAY_MAX_KEYS,
                    help=f"decimate to at most this many keys, all channels together (default {REPLAY_MAX_KEYS})")
    rp.set_defaults(func=run_replay)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _load(path: Path) -> dict[str, Any]:
    from likeness.cli import CliError
    from runtime.recording import load_recording

    try:
        return load_recording(path)
    except ValueError as exc:
        raise CliError(str(exc)) from exc


def _span(rec: dict[str, Any]) -> float:
    t = rec["t"]
    return float(t[-1] - t[0]) if len(t) else 0.0


def run_list(args: argparse.Namespace) -> int:
    from likeness.cli import CliError
    from runtime.recording import recording_summary

    if not args.dir.is_dir():
        raise CliError(f"{args.dir}: not a folder")
    files = sorted(p for p in args.dir.iterdir() if p.suffix in SUFFIXES and p.is_file())
    print(f"{'file':<40}{'frames':>10}{'span [s]':>12}")
    for path in files:
        try:
            frames, span = recording_summary(path)
        except ValueError as exc:
            print(f"{path.name:<40}  unreadable: {exc}")
            continue
        print(f"{path.name:<40}{frames:>10}{span:>12.3f}")
    if not files:
        print(f"(no recordings in {args.dir})")
    return 0


def run_info(args: argparse.Namespace) -> int:
    rec = _load(args.file)
    n = len(rec["t"])
    print(f"file:     {args.file}")
    print(f"frames:   {n}")
    print(f"span:     {_span(rec):.3f} s" + (f" ({rec['t'][0]:.3f} .. {rec['t'][-1]:.3f})" if n else ""))
    partial = rec["meta"].get("partial_bytes", 0)
    if partial:
        print(f"partial:  {partial} bytes after the last complete frame (ignored)")
    print(f"channels: {len(rec['names'])}")
    for name, unit in zip(rec["names"], rec["units"], strict=True):
        print(f"  {name} [{unit}]")
    extra = {k: v for k, v in rec["meta"].items() if k not in ("samples", "partial_bytes")}
    if extra:
        print("meta:     " + ", ".join(f"{k}={v}" for k, v in sorted(extra.items())))
    return 0


def replay_clip(rec: dict[str, Any], name: str, max_keys: int = REPLAY_MAX_KEYS) -> dict[str, Any]:
    """The protocol clip map of a recording's commanded curves (linear), decimated to at most ``max_keys`` keys."""
    import math

    import numpy as np

    t = np.asarray(rec["t"], dtype=float)
    cmd = np.asarray(rec["commanded"], dtype=float)
    channels: dict[str, Any] = {}
    per_channel = max(2, max_keys // max(1, len(rec["names"])))
    for j, ch in enumerate(rec["names"]):
        ok = np.isfinite(cmd[:, j]) & np.isfinite(t)
        tj, vj = t[ok] - (t[0] if len(t) else 0.0), cmd[ok, j]
        if not len(tj):
            continue
        stride = max(1, math.ceil(len(tj) / per_channel))
        idx = np.unique(np.r_[np.arange(0, len(tj), stride), len(tj) - 1])
        keep = idx[np.r_[True, np.diff(tj[idx]) > 0]]  # strictly increasing times
        channels[ch] = {"interp": "linear", "keys": np.column_stack([tj[keep], vj[keep]]).tolist()}
    return {"name": name[:128], "channels": channels}


def run_replay(args: argparse.Namespace) -> int:
    from likeness.cli import CliError
    from models.clip import ClipError, clip_from_dict

    if not args.speed > 0 or args.max_keys < 2:
        raise CliError("--speed must be positive and --max-keys at least 2")
    rec = _load(args.file)
    data = replay_clip(rec, f"replay-{args.file.stem}", args.max_keys)
    if not data["channels"]:
        raise CliError(f"{args.file}: no commanded samples to replay")
    try:
        clip = clip_from_dict(data, where=str(args.file))
    except ClipError as exc:
        raise CliError(str(exc)) from exc
    with connect(args) as client:
        if args.enable and call(client, "status")["lifecycle"] == "inactive":
            call(client, "enable")
        call(client, "load_clip", clip=data)
        reply = call(client, "play", clip=clip.name, speed=args.speed)
    print(f"replaying {clip.name!r}: {len(clip.channels)} channels, {clip.key_count()} keys, "
          f"{reply['duration']:.2f} s from daemon time {reply['start']:.3f}")
    return 0
