"""``likeness stream``: send a clip file (JSON or CSV) to a running daemon, as timestamped frames or as a clip."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from runtime.cli._client import add_client_options, connect

if TYPE_CHECKING:
    from models.client import Client
    from models.clip import Clip


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The clip, the client options and how to send it."""
    p = parser
    p.add_argument("clip", type=Path, help="clip file: .json (keyframe curves) or .csv (time + one column per channel)")
    add_client_options(p)
    p.add_argument("--fps", type=float, default=100.0, help="frames per second when streaming (default 100)")
    p.add_argument("--upload", action="store_true",
                   help="send the clip once (load_clip + play) instead of streaming sampled frames")
    p.add_argument("--loop", action="store_true", help="with --upload: loop the clip")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    p.add_argument("--interp", choices=("linear", "step"), default="linear", help="CSV interpolation")
    p.add_argument("--enable", action="store_true", help="enable torque first if the head is inactive")


def run(args: argparse.Namespace) -> int:
    """Stream the clip frame by frame at --fps, or upload and play it (--upload)."""
    from models.clip import ClipError, clip_file_as_dict, clip_from_dict
    from models.errors import UsageError

    if not args.fps > 0 or not args.speed > 0:
        raise UsageError("--fps and --speed must be positive")
    try:
        data = clip_file_as_dict(args.clip, args.interp)
        clip = clip_from_dict(data, where=str(args.clip))
    except ClipError as exc:
        raise UsageError(str(exc)) from exc
    with connect(args) as client:
        if args.enable and client.call("status")["lifecycle"] == "inactive":
            client.call("enable")
        if args.upload:
            client.call("load_clip", clip=data)
            reply = client.call("play", clip=clip.name, loop=args.loop, speed=args.speed)
            print(f"playing {clip.name!r} ({reply['duration']:.2f} s) from daemon time {reply['start']:.3f}")
            return 0
        offset, rtt = client.clock_offset()
        sent, accepted, late = _stream_frames(client, clip, args.fps, args.speed, offset)
    print(f"streamed {sent} frames of {clip.name!r} at {args.fps:g} fps: {accepted} accepted, {late} late "
          f"(clock offset {offset * 1e3:.3f} ms, round trip {rtt * 1e6:.0f} us)")
    return 0


def _stream_frames(client: Client, clip: Clip, fps: float, speed: float, offset: float) -> tuple[int, int, int]:
    """Send the clip sampled at ``fps`` as one-frame ``stream`` requests, each at its wall-clock time stamped in
    daemon time (``offset``); shows progress on a terminal. Returns frames sent, accepted and late."""
    import sys
    import time

    channels = sorted(clip.channels)
    duration = clip.duration / speed
    step = 1.0 / fps
    t0 = time.monotonic()
    sent = accepted = late = 0
    k = 0
    while True:
        t = k * step
        if t > duration + 1e-9:
            break
        wake = t0 + t
        delay = wake - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        values = clip.sample(min(t * speed, clip.duration))
        frame = [wake + offset] + [values[c] for c in channels]
        reply = client.call("stream", channels=channels, frames=[frame])
        sent += 1
        accepted += reply["accepted"]
        late += reply["late"]
        k += 1
        if k % max(1, int(fps / 4)) == 0 and sys.stdout.isatty():
            print(f"\rstreaming {clip.name}: {t:6.2f}/{duration:.2f} s  {accepted} accepted, {late} late",
                  end="", flush=True)
    if sys.stdout.isatty():
        print()
    return sent, accepted, late
