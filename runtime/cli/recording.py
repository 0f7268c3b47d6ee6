"""``likeness recording list|info|replay``: what the daemon recorded, and playing its commanded curves again."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from runtime.cli._client import add_client_options, connect

#: Keys sent by ``replay`` at most (all channels together): ``runtime.recording.REPLAY_MAX_KEYS``, kept import-free.
REPLAY_MAX_KEYS = 40_000
SUFFIXES = (".lrec", ".npz")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``list``, ``info`` and ``replay`` actions and their options."""
    rsub = parser.add_subparsers(dest="recording_command", metavar="ACTION")
    ls = rsub.add_parser("list", help="recordings in a folder with frame count and time span")
    ls.add_argument("dir", type=Path, nargs="?", default=Path("recordings"),
                    help="folder (default: ./recordings, the daemon's default [runtime] record_dir)")
    info = rsub.add_parser("info", help="frame count, time span and channels of one recording")
    info.add_argument("file", type=Path)
    rp = rsub.add_parser("replay", help="send a recording's commanded curves to a daemon as a clip and play it")
    rp.add_argument("file", type=Path)
    add_client_options(rp)
    rp.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    rp.add_argument("--enable", action="store_true", help="enable torque first if the head is inactive")
    rp.add_argument("--max-keys", type=int, default=REPLAY_MAX_KEYS,
                    help=f"decimate to at most this many keys, all channels together (default {REPLAY_MAX_KEYS})")
    parser.set_defaults(recording_help=parser.print_help)


def run(args: argparse.Namespace) -> int:
    """Run the chosen action; without one, print the command's help (exit 2)."""
    actions = {"list": run_list, "info": run_info, "replay": run_replay}
    if args.recording_command is None:
        args.recording_help()
        return 2
    return actions[args.recording_command](args)


def _load(path: Path) -> dict[str, Any]:
    from models.errors import UsageError
    from runtime.recording import load_recording

    try:
        return load_recording(path)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc


def _span(rec: dict[str, Any]) -> float:
    t = rec["t"]
    return float(t[-1] - t[0]) if len(t) else 0.0


def run_list(args: argparse.Namespace) -> int:
    """The recordings of a folder with frame count and time span."""
    from models.errors import UsageError
    from runtime.recording import recording_summary

    if not args.dir.is_dir():
        raise UsageError(f"{args.dir}: not a folder")
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
    """Frame count, time span, channels and metadata of one recording."""
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


def run_replay(args: argparse.Namespace) -> int:
    """Send a recording's commanded curves to the daemon as a clip and play it."""
    from models.clip import ClipError, clip_from_dict
    from models.errors import UsageError
    from runtime.recording import replay_clip

    if not args.speed > 0 or args.max_keys < 2:
        raise UsageError("--speed must be positive and --max-keys at least 2")
    rec = _load(args.file)
    data = replay_clip(rec, f"replay-{args.file.stem}", args.max_keys)
    if not data["channels"]:
        raise UsageError(f"{args.file}: no commanded samples to replay")
    try:
        clip = clip_from_dict(data, where=str(args.file))
    except ClipError as exc:
        raise UsageError(str(exc)) from exc
    with connect(args) as client:
        if args.enable and client.call("status")["lifecycle"] == "inactive":
            client.call("enable")
        client.call("load_clip", clip=data)
        reply = client.call("play", clip=clip.name, speed=args.speed)
    print(f"replaying {clip.name!r}: {len(clip.channels)} channels, {clip.key_count()} keys, "
          f"{reply['duration']:.2f} s from daemon time {reply['start']:.3f}")
    return 0
