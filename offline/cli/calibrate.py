"""``likeness calibrate``: measure a head's link map m(p) with a marker tracker.

Examples::

    likeness calibrate --config heads/sample/head.toml --tracker sim --out runs/cal1
    likeness calibrate --config head.toml --tracker zmq://tcp://10.0.0.5:7000 --out runs/cal2
    likeness calibrate --config head.toml --tracker runs/cal2/capture.csv --out runs/refit \\
        --journal runs/cal2/journal.jsonl

The head is driven through a daemon: a running one with ``--daemon``, otherwise ``likeness daemon`` started for
the config as a child process (it starts the bus emulators when the config says ``simulated = true``); or by ideal
motors with ``--ideal-motors``. ``--tracker sim`` runs the sample head's simulated tracker (``likeness sim
tracker``) as a child process and reads its capture stream. ``--tracker FILE.csv`` refits from a capture export and
the journal of the run that drove the head. Re-running with the same ``--out`` resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from models.headspec import HeadSpec
    from offline.calibration.heads import HeadDriver
    from offline.calibration.processes import ChildProcess, SimTrackerProcess
    from offline.calibration.workflow import CalibrationResult, CalibrationSettings


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``likeness calibrate``."""
    p.add_argument("--config", required=True, type=Path, help="head config TOML")
    p.add_argument("--tracker", required=True, help="sim | FILE.csv | zmq://ENDPOINT")
    p.add_argument("--out", required=True, type=Path, help="run directory (outputs, journal; resumes if present)")
    p.add_argument("--samples", type=int, default=120, help="random poses after the sweeps (default 120)")
    p.add_argument("--seed", type=int, default=0, help="seed of the plan and the simulated tracker")
    p.add_argument("--link-model", choices=("auto", "quadratic", "mechanism"), default="auto",
                   help="auto: fit the free quadratic map and the head's mechanism file ([paths] mechanism), keep the "
                   "smaller hold-out error (default); quadratic: the map only; mechanism: the fitted mechanism")
    p.add_argument("--fit-joints", action="store_true",
                   help="the mechanism fit moves joint positions too (slower), besides zero offsets and rod lengths")
    p.add_argument("--daemon", metavar="ENDPOINT",
                   help="drive through a running daemon (e.g. tcp://127.0.0.1:5555); default: start one")
    p.add_argument("--sweep-levels", type=int, default=5, help="levels per actuator sweep (default 5)")
    p.add_argument("--holdout", type=float, default=0.25, help="fraction of random poses held out (default 0.25)")
    p.add_argument("--frames", type=int, default=8, help="tracker frames recorded per pose (default 8)")
    p.add_argument("--speed", type=float, default=0.3, help="fraction of max velocity used to move (default 0.3)")
    p.add_argument("--no-discover", action="store_true", help="skip travel-limit discovery")
    p.add_argument("--discover-step", type=float, default=3.0, help="limit discovery step in degrees (default 3)")
    p.add_argument("--journal", type=Path, help="with --tracker FILE.csv: journal of the recorded run")
    p.add_argument("--ideal-motors", action="store_true", help="with --tracker sim: ideal motors, no buses")
    p.add_argument("--noise-mm", type=float, default=0.2, help="simulated tracker position noise (default 0.2)")
    p.add_argument("--noise-deg", type=float, default=0.2, help="simulated tracker rotation noise (default 0.2)")
    p.add_argument("--dropout", type=float, default=0.02, help="simulated tracker dropout rate (default 0.02)")
    p.add_argument("--outliers", type=float, default=0.01, help="simulated tracker outlier rate (default 0.01)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Run or resume a calibration; prints the per-link report. Errors are ``models.errors`` kinds."""
    from models.errors import BadValue, LikenessError, UsageError
    from models.headspec import load_head
    from offline.calibration.workflow import calibrate_replay

    if args.samples < 0 or args.frames < 2 or args.sweep_levels < 2 or not 0 <= args.holdout < 1:
        raise UsageError("need --samples >= 0, --frames >= 2, --sweep-levels >= 2 and 0 <= --holdout < 1")
    if not 0 < args.speed <= 1:
        raise UsageError(f"--speed must be in (0, 1], got {args.speed}")
    tracker = args.tracker
    replay = tracker.lower().endswith(".csv")
    if not (replay or tracker == "sim" or tracker.startswith("zmq://")):
        raise UsageError(f"--tracker must be sim, a .csv capture export or zmq://ENDPOINT, got {tracker!r}")
    if args.ideal_motors and tracker != "sim":
        raise UsageError("--ideal-motors only works with --tracker sim")
    head = load_head(args.config)
    try:
        if replay:
            journal = args.journal or (args.out / "journal.jsonl")
            if not Path(tracker).exists():
                raise UsageError(f"capture file not found: {tracker}")
            if not journal.exists():
                raise UsageError(f"journal not found: {journal} (pass --journal of the run that drove the head)")
            reference = _sample_reference(head) if head.name == "sample" else None
            settings = _settings(args, "capture replay")
            result = calibrate_replay(head, tracker, journal, args.out, settings, reference=reference)
        else:
            result = _calibrate_live(args, head)
    except ValueError as exc:  # a bad value met on the way (SpecError is a LikenessError already)
        if isinstance(exc, LikenessError):
            raise
        raise BadValue(str(exc)) from exc
    _print_report(result)
    return 0


def _settings(args: argparse.Namespace, driver: str) -> CalibrationSettings:
    """The run's settings from the options; ``driver`` says how the head is driven (provenance)."""
    from offline.calibration.workflow import CalibrationSettings

    return CalibrationSettings(
        samples=args.samples, seed=args.seed, sweep_levels=args.sweep_levels, holdout_fraction=args.holdout,
        frames_per_pose=args.frames, discover=not args.no_discover, discover_step=math.radians(args.discover_step),
        progress=not args.no_progress, tracker=args.tracker, tie_groups=not args.ideal_motors, driver=driver,
        link_model=args.link_model, fit_joints=args.fit_joints,
    )


def _calibrate_live(args: argparse.Namespace, head: HeadSpec) -> CalibrationResult:
    """Start what the run needs (daemon, simulated tracker), drive the head through the plan, stop them again."""
    from offline.calibration.capture import ZmqSource
    from offline.calibration.heads import DaemonHead, KinematicHead
    from offline.calibration.processes import SimTrackerProcess, start_daemon
    from offline.calibration.workflow import calibrate_live

    sim = args.tracker == "sim"
    reference = _sample_reference(head) if sim else None
    daemon: ChildProcess | None = None
    tracker: SimTrackerProcess | None = None
    driver: HeadDriver | None = None
    source: ZmqSource | None = None
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        endpoint = args.daemon
        if endpoint is None and not args.ideal_motors:
            daemon, endpoint = start_daemon(args.config, args.out)
        if sim:
            tracker = SimTrackerProcess(args.config, args.out, None if args.ideal_motors else endpoint,
                                        seed=args.seed, noise_mm=args.noise_mm, noise_deg=args.noise_deg,
                                        dropout=args.dropout, outliers=args.outliers)
            stream = tracker.endpoint
        else:
            stream = args.tracker[len("zmq://"):]
            if "://" not in stream:
                stream = f"tcp://{stream}"
        source = ZmqSource(stream)
        if tracker is not None and args.ideal_motors:
            driver = KinematicHead(head, show=tracker.show)
            how = "ideal-motors"
        else:
            driver = DaemonHead(endpoint, head, speed_fraction=args.speed, reset_start_fault=daemon is not None)
            how = f"daemon {endpoint}" + ("" if args.daemon else " (started for the run)")
        return calibrate_live(head, driver, source, args.out, _settings(args, how), reference=reference)
    finally:
        for part in (source, driver, tracker, daemon):
            if part is not None:
                part.close()


def _sample_reference(head: HeadSpec) -> dict[str, np.ndarray]:
    """The simulated mechanism's design rest poses (the zero-offset reference): the head's mechanism file (default
    the sample head's), whose motors and links must be the head's."""
    from models.errors import BadValue
    from models.mechanism import SAMPLE_MECHANISM, Mechanism

    mech = Mechanism.load(head.path("mechanism") or SAMPLE_MECHANISM)
    missing = sorted(set(head.actuator_names) ^ set(mech.actuators))
    links = sorted({link.name for link in head.links} ^ set(mech.links))
    if missing or links:
        raise BadValue(f"--tracker sim simulates the sample head's mechanism; head {head.name!r} differs in "
                       f"actuators {missing} / links {links}")
    return mech.rest_poses()


def _print_report(result: CalibrationResult) -> None:
    r = result.report
    print(f"link map: {result.out_dir / 'linkmap.json'}")
    print(f"{'link':<14} {'rms mm':>8} {'max mm':>8} {'rms deg':>8}  actuators")
    for name, v in r["links"].items():
        acts = ", ".join(r["detected_actuators"][name]) or "-"
        print(f"{name:<14} {v['rms_mm']:8.3f} {v['max_mm']:8.3f} {v['rms_deg']:8.3f}  {acts}")
    hold = r["holdout_rms_mm"]
    floor = r.get("noise_floor_mm")
    print(f"hold-out RMS {hold:.3f} mm" if hold is not None else "no hold-out poses",
          f"(pose noise floor {floor:.3f} mm)" if floor else "")
    if (result.out_dir / "proposed_config.toml").exists():
        print(f"proposed config change: {result.out_dir / 'proposed_config.toml'}")
    print(f"report: {result.out_dir / 'report.json'}, plot: {result.out_dir / 'report.png'}")
