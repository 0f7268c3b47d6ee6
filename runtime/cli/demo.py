"""``likeness demo``: the sample head on emulated hardware plays a bundled performance; prints tracking error and
loop statistics and writes a plot of commanded versus measured curves (what ``make demo`` runs)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from runtime.cli._client import SAMPLE_HEAD

if TYPE_CHECKING:
    from models.headspec import HeadSpec
    from runtime.demo import DemoRun

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

    from drivers.errors import BusError
    from models.clip import ClipError, clip_file_as_dict, clip_from_dict
    from models.errors import SpecError, UsageError
    from models.headspec import load_head
    from runtime.cli._client import start_error
    from runtime.daemon import Daemon, DaemonStartError
    from runtime.demo import demo_overrides, play_performance

    head = load_head(args.config)
    clips = []
    try:
        for path in args.performance:
            data = clip_file_as_dict(path)
            clips.append((data, clip_from_dict(data, where=str(path))))
    except ClipError as exc:
        raise UsageError(str(exc)) from exc
    print(f"head {head.name!r}: {len(head.actuators)} actuators on "
          + ", ".join(f"{b} ({s.driver}{', emulated' if s.simulated else ''})" for b, s in head.buses.items()))
    if not any(s.simulated for s in head.buses.values()):
        print("warning: no bus of this head is simulated: the demo moves REAL motors", file=sys.stderr)
    try:
        daemon = Daemon(head, demo_overrides(args.out, args.rate, realtime=not args.no_realtime))
        daemon.start()
    except (SpecError, BusError, DaemonStartError, OSError) as exc:
        raise start_error(exc, "cannot start the daemon: ") from exc
    try:
        print(f"daemon up at {daemon.cfg.runtime.rate_hz:g} Hz; commands {daemon.command_endpoint}; "
              f"{daemon.realtime_status}")
        result = play_performance(daemon.command_endpoint, daemon.telemetry_endpoint, clips)
    finally:
        daemon.stop()
    if result.fault is not None:
        why = result.fault.get("message") or result.fault.get("reason")
        if result.fault.get("source") == "timeout":
            print(f"FEEDBACK FROZE: {why}", file=sys.stderr)
        print(f"performance stopped by {result.fault['event']}: {why}")
        _print_feedback(result)
        return 1
    _print_results(head, result, args.out)
    return 0


def _print_results(head: HeadSpec, result: DemoRun, out: Path) -> None:
    """Each clip's tracking error and plot, the skin-strain guard's refusals and the loop's statistics."""
    from runtime.cli.plot import print_errors
    from runtime.recording import load_recording, plot_recording, tracking_errors

    for clip, rec_reply in result.recordings:
        rec = load_recording(rec_reply["path"])
        print(f"tracking error of {clip.name!r} (commanded vs measured):")
        print_errors(tracking_errors(rec, settle_s=0.0))
        _print_feedback(result, clip.name)
        png = plot_recording(rec, out / f"{clip.name}.png", title=f"{head.name}: {clip.name} — commanded vs measured")
        print(f"recording: {rec_reply['path']} ({rec_reply['samples']} samples)\nplot: {png}")
    status: dict[str, Any] = result.status
    guard = status.get("guard")
    if guard and guard.get("refused"):
        print(f"skin-strain guard: {guard['refused']} cycles' targets limited or held where the predicted skin strain "
              "would leave the material's validated range (docs/skin_guard.md)")
    loop = status["loop"]
    print(f"loop: {loop['rate_hz']:g} Hz, {loop['cycles']} cycles, {loop['missed']} missed deadlines; jitter "
          f"p50 {loop.get('jitter_p50_us', 0):.1f} us, p99 {loop.get('jitter_p99_us', 0):.1f} us, max "
          f"{loop.get('jitter_max_us', 0):.1f} us; cycle work p50 {loop.get('work_p50_us', 0):.0f} us, "
          f"p99 {loop.get('work_p99_us', 0):.0f} us")
    causes: dict[str, int] = {}
    for seen in result.misses.values():
        for cause, n in seen.by_cause.items():
            causes[cause] = causes.get(cause, 0) + n
    if causes:
        print("  missed deadlines during the performances, by what held the loop (docs/operations.md, the soak): "
              + ", ".join(f"{k} {v}" for k, v in sorted(causes.items(), key=lambda kv: -kv[1])))
    elif loop["missed"]:
        print("  none of the missed deadlines came during the performances (they came before, between or after them)")


def _print_feedback(result: DemoRun, only: str | None = None) -> None:
    """Per performance, the largest feedback age of each bus and how often it was reported late."""
    for name, seen in result.feedback.items():
        if only is not None and name != only:
            continue
        ages = ", ".join(f"{bus} {age * 1e3:.0f} ms" for bus, age in sorted(seen.max_age.items())) or "none seen"
        line = f"feedback of {name!r}: largest age {ages}"
        if seen.late:
            line += "; late: " + ", ".join(f"{bus} {n}x (limit {seen.limit.get(bus, 0) * 1e3:.0f} ms)"
                                           for bus, n in sorted(seen.late.items()))
        print(line)
