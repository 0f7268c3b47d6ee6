"""``likeness calibrate``: measure a head's link map m(p) with a marker tracker.

Examples::

    likeness calibrate --config heads/sample/head.toml --tracker sim --out runs/cal1
    likeness calibrate --config head.toml --tracker zmq://tcp://10.0.0.5:7000 --out runs/cal2
    likeness calibrate --config head.toml --tracker runs/cal2/capture.csv --out runs/refit \
        --journal runs/cal2/journal.jsonl

``--tracker sim`` simulates the sample head's mechanism and tracker; the head is driven through its buses
(emulated when the config says ``simulated = true``), through a running daemon with ``--daemon``, or with
ideal motors with ``--ideal-motors``. ``--tracker FILE.csv`` refits from a capture export and the journal of
the run that drove the head. Re-running with the same ``--out`` resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``calibrate``."""
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--config", required=True, type=Path, help="head config TOML")
    p.add_argument("--tracker", required=True, help="sim | FILE.csv | zmq://ENDPOINT")
    p.add_argument("--out", required=True, type=Path, help="run directory (outputs, journal; resumes if present)")
    p.add_argument("--samples", type=int, default=120, help="random poses after the sweeps (default 120)")
    p.add_argument("--seed", type=int, default=0, help="seed of the plan and the simulated tracker")
    p.add_argument("--daemon", metavar="ENDPOINT", help="drive through a running daemon (e.g. tcp://127.0.0.1:5555)")
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
    """Run or resume a calibration; prints the per-link report."""
    from models.errors import SpecError, UsageError
    from models.headspec import load_head
    from runtime.calibration.capture import CalibrationError
    from runtime.calibration.workflow import CalibrationSettings, calibrate_live, calibrate_replay

    if args.samples < 0 or args.frames < 2 or args.sweep_levels < 2 or not 0 <= args.holdout < 1:
        raise UsageError("need --samples >= 0, --frames >= 2, --sweep-levels >= 2 and 0 <= --holdout < 1")
    if not 0 < args.speed <= 1:
        raise UsageError(f"--speed must be in (0, 1], got {args.speed}")
    try:
        head = load_head(args.config)
    except SpecError as exc:
        raise UsageError(str(exc)) from exc
    settings = CalibrationSettings(
        samples=args.samples, seed=args.seed, sweep_levels=args.sweep_levels, holdout_fraction=args.holdout,
        frames_per_pose=args.frames, discover=not args.no_discover, discover_step=math.radians(args.discover_step),
        progress=not args.no_progress, tracker=args.tracker,
        tie_groups=bool(args.daemon) and not args.ideal_motors,
        driver="ideal-motors" if args.ideal_motors else (f"daemon {args.daemon}" if args.daemon else "hardware"),
    )
    tracker = args.tracker
    reference = None
    driver = None
    source = None
    try:
        if tracker.lower().endswith(".csv"):
            journal = args.journal or (args.out / "journal.jsonl")
            if not Path(tracker).exists():
                raise UsageError(f"capture file not found: {tracker}")
            if not journal.exists():
                raise UsageError(f"journal not found: {journal} (pass --journal of the run that drove the head)")
            if head.name == "sample":
                reference = _sample_reference(head)
            result = calibrate_replay(head, tracker, journal, args.out, settings, reference=reference)
        else:
            driver = _driver(args, head)
            if tracker == "sim":
                from runtime.calibration.capture import SimSource
                from sim_hardware.tracker import SimTracker, TrackerNoise

                mech = _sample_mechanism(head)
                reference = mech.rest_poses()
                noise = TrackerNoise(position_sigma=args.noise_mm * 1e-3, rotation_sigma=math.radians(args.noise_deg),
                                     dropout_rate=args.dropout, outlier_rate=args.outliers)
                source = SimSource(SimTracker(mech, driver.positions, noise=noise, seed=args.seed))
            elif tracker.startswith("zmq://"):
                from runtime.calibration.capture import ZmqSource

                endpoint = tracker[len("zmq://"):]
                if "://" not in endpoint:
                    endpoint = f"tcp://{endpoint}"
                source = ZmqSource(endpoint)
            else:
                raise UsageError(f"--tracker must be sim, a .csv capture export or zmq://ENDPOINT, got {tracker!r}")
            result = calibrate_live(head, driver, source, args.out, settings, reference=reference)
    except (CalibrationError, SpecError, ValueError) as exc:
        raise UsageError(str(exc)) from exc
    finally:
        if source is not None:
            source.close()
        if driver is not None:
            driver.close()
    _print_report(result)
    return 0


def _sample_mechanism(head):
    from models.errors import UsageError
    from sim_hardware.mechanism import sample_mechanism

    mech = sample_mechanism(head)
    missing = sorted(set(head.actuator_names) ^ set(mech.actuators))
    links = sorted({link.name for link in head.links} ^ set(mech.links))
    if missing or links:
        raise UsageError(f"--tracker sim simulates the sample head's mechanism; head {head.name!r} differs in "
                       f"actuators {missing} / links {links}")
    return mech


def _sample_reference(head):
    return _sample_mechanism(head).rest_poses()


def _driver(args: argparse.Namespace, head):
    from models.errors import UsageError
    from runtime.calibration.heads import DaemonHead, HardwareHead, KinematicHead

    if args.ideal_motors:
        if args.tracker != "sim":
            raise UsageError("--ideal-motors only works with --tracker sim")
        return KinematicHead(head)
    if args.daemon:
        return DaemonHead(args.daemon, head, speed_fraction=args.speed)
    try:
        from runtime.hardware import Hardware
    except ImportError as exc:
        raise UsageError(f"cannot reach the head's buses ({exc}); use --daemon or --ideal-motors") from exc
    try:
        hw = Hardware.from_head(head)
    except Exception as exc:
        raise UsageError(f"cannot start the head's buses: {exc}") from exc
    try:
        return HardwareHead(hw, head, speed_fraction=args.speed)
    except Exception as exc:
        hw.close()
        raise UsageError(f"cannot enable the head's buses: {exc}") from exc


def _print_report(result) -> None:
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
