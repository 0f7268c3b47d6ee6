"""``likeness demo``: the sample head on emulated hardware plays a bundled performance; prints tracking error and
loop statistics and writes a plot of commanded versus measured curves (what ``make demo`` runs)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from runtime.cli._client import SAMPLE_HEAD

if TYPE_CHECKING:
    from models.client import Client, Telemetry
    from runtime.curves import Clip

#: Played in order: actuator curves, then blendshape (``arkit.*``) curves solved through the skin predictor.
PERFORMANCES = [SAMPLE_HEAD.parent / "performances" / name for name in ("expressive.json", "blendshapes.json")]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The head, the clips, the output folder and the loop's rate and priority."""
    p = parser
    p.add_argument("--config", type=Path, default=SAMPLE_HEAD, help="head spec (default: the sample head)")
    p.add_argument("--performance", type=Path, nargs="+", default=PERFORMANCES,
                   help="clips to play in order (JSON or CSV; default: the sample head's two performances)")
    p.add_argument("--out", type=Path, default=Path("demo-output"), help="directory for recording and plot")
    p.add_argument("--rate", type=float, default=None, help="loop rate in Hz (default: from the head spec)")
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")


def run(args: argparse.Namespace) -> int:
    """Start the daemon on the head, play each clip while recording it, then print and plot how it tracked."""
    import sys
    import time

    from drivers.errors import BusError
    from models.client import Client, Telemetry
    from models.errors import SpecError, UsageError
    from models.headspec import load_head
    from runtime.cli._client import start_error
    from runtime.cli.plot import print_errors
    from runtime.curves import ClipError, clip_file_as_dict, clip_from_dict
    from runtime.daemon import Daemon, DaemonStartError
    from runtime.recording import load_recording, plot_recording, tracking_errors

    head = load_head(args.config)
    clips = []
    try:
        for path in args.performance:
            data = clip_file_as_dict(path)
            clips.append((data, clip_from_dict(data, where=str(path))))
    except ClipError as exc:
        raise UsageError(str(exc)) from exc
    simulated = [b for b, s in head.buses.items() if s.simulated]
    overrides: dict[str, object] = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                                    "runtime.record_dir": str(args.out)}
    if args.rate:
        overrides["runtime.rate_hz"] = args.rate
    if args.no_realtime:
        overrides["runtime.realtime"] = False
    print(f"head {head.name!r}: {len(head.actuators)} actuators on "
          + ", ".join(f"{b} ({s.driver}{', emulated' if s.simulated else ''})" for b, s in head.buses.items()))
    if not simulated:
        print("warning: no bus of this head is simulated: the demo moves REAL motors", file=sys.stderr)
    try:
        daemon = Daemon(head, overrides)
        daemon.start()
    except (SpecError, BusError, DaemonStartError, OSError) as exc:
        raise start_error(exc, "cannot start the daemon: ") from exc
    recordings = []
    fault = None
    try:
        print(f"daemon up at {daemon.cfg.runtime.rate_hz:g} Hz; commands {daemon.command_endpoint}; "
              f"{daemon.realtime_status}")
        with Client(daemon.command_endpoint, timeout=10.0) as client, Telemetry(daemon.telemetry_endpoint) as tel:
            client.call("enable")
            time.sleep(0.2)  # let the telemetry subscription settle
            for data, clip in clips:
                fault = _play(client, tel, data, clip)
                rec_reply = client.call("record", action="stop")
                if fault is not None:
                    break
                recordings.append((clip, rec_reply))
            status = client.call("status")
            if fault is None:
                client.call("disable")
    finally:
        daemon.stop()
    if fault is not None:
        print(f"performance stopped by {fault['event']}: {fault.get('message') or fault.get('reason')}")
        return 1
    for clip, rec_reply in recordings:
        rec = load_recording(rec_reply["path"])
        print(f"tracking error of {clip.name!r} (commanded vs measured):")
        print_errors(tracking_errors(rec, settle_s=0.0))
        png = plot_recording(rec, args.out / f"{clip.name}.png",
                             title=f"{head.name}: {clip.name} — commanded vs measured")
        print(f"recording: {rec_reply['path']} ({rec_reply['samples']} samples)\nplot: {png}")
    guard = status.get("guard")
    if guard and guard.get("refused"):
        print(f"skin-strain guard: {guard['refused']} cycles' targets limited or held where the predicted skin strain "
              "would leave the material's validated range (docs/skin_guard.md)")
    loop = status["loop"]
    print(f"loop: {loop['rate_hz']:g} Hz, {loop['cycles']} cycles, {loop['missed']} missed deadlines; jitter "
          f"p50 {loop.get('jitter_p50_us', 0):.1f} us, p99 {loop.get('jitter_p99_us', 0):.1f} us, max "
          f"{loop.get('jitter_max_us', 0):.1f} us; cycle work p50 {loop.get('work_p50_us', 0):.0f} us, "
          f"p99 {loop.get('work_p99_us', 0):.0f} us")
    return 0


def _play(client: Client, tel: Telemetry, data: dict[str, Any], clip: Clip) -> dict[str, Any] | None:
    """Load, record and play one clip with a progress bar; returns the fault or e-stop event that cut it short."""

    reply = client.call("load_clip", clip=data)
    print(f"performance {clip.name!r}: {reply['duration']:.2f} s, {len(reply['channels'])} channels, "
          f"{reply['keys']} keys")
    client.call("record", action="start", name=clip.name)
    start = client.call("play", clip=clip.name)["start"]
    duration = reply["duration"]
    shown = -1
    while True:
        msg = tel.recv(0.5)
        now = client.call("clock")["t_send"]
        if msg is not None and msg[0] == "event" and msg[1]["event"] in ("fault", "estop"):
            print()
            return msg[1]
        pct = int(min(1.0, max(0.0, (now - start) / duration)) * 100)
        if pct // 5 != shown:
            shown = pct // 5
            bar = "#" * (pct // 5) + "." * (20 - pct // 5)
            print(f"\r  playing [{bar}] {pct:3d}%  {now - start:5.2f}/{duration:.2f} s", end="", flush=True)
        if now - start > duration + 0.5:
            print()
            return None
