"""CPU of the CANopen emulator (``likeness sim canopen``) serving the sample head's drives, against an older version
of the emulator measured in the same run.

Each round starts the emulator of this tree and of ``--baseline-rev`` (exported with ``git archive`` into a temporary
folder) in turn, with ``--drives`` CiA 402 drives (heartbeat 250 ms, as the sample head writes it), and drives them
from this process with the ``canopen402`` driver at ``--rate`` Hz (write targets + SYNC, wait for every TPDO, read),
as the daemon's bus process does. The emulator's CPU is read from ``/proc/PID/stat`` (all its threads) over the
driven window and over an idle window with no client. Rounds alternate the two versions so that the machine's load
falls on both; the ratio old / new is the figure to compare, absolute percentages move with the load.

Run: ``python benchmarks/canopen_emulator.py [--drives 7] [--rate 250] [--seconds 10] [--rounds 2] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: The emulator before its direct socketcand path, one timer thread tick and batched replies.
BASELINE_REV = "be0fcfe"
TREE_PARTS = ("likeness", "sim_hardware", "models", "drivers")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (all threads) from ``/proc/PID/stat``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def export_rev(rev: str, dest: Path) -> str:
    """Write the emulator's packages at git revision ``rev`` into ``dest``; returns the full commit id."""
    commit = subprocess.run(["git", "rev-parse", rev], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    archive = subprocess.run(["git", "archive", rev, *TREE_PARTS], cwd=ROOT, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return commit.strip()


def start_emulator(tree: Path, drives: int) -> tuple[subprocess.Popen[str], dict[str, Any]]:
    """``likeness sim canopen`` from ``tree``; returns the process and the driver options that reach it."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    proc = subprocess.Popen([sys.executable, "-m", "likeness", "sim", "canopen", "--nodes", f"1-{drives}", "--port",
                             "0", "--heartbeat-ms", "250", "--watch-parent"], cwd=tree, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline() if proc.stdout else ""
    match = re.search(r"on socketcand ([\d.]+):(\d+) channel (\S+)", line)
    if not match:
        proc.kill()
        raise RuntimeError(f"emulator in {tree} did not start: {line!r}")
    return proc, {"interface": "socketcand", "host": match.group(1), "port": int(match.group(2)),
                  "channel": match.group(3), "heartbeat_timeout_s": 2.0, "feedback_timeout_s": 1.0,
                  "sdo_timeout_s": 2.0, "state_timeout_s": 2.0}  # patient: a loaded host stalls the emulator


def drive(options: dict[str, Any], drives: int, rate: float, seconds: float, pid: int) -> dict[str, float]:
    """Cycle the drives at ``rate`` for ``seconds``; the emulator's CPU % and the cycles' figures."""
    from drivers.base import MotorConfig
    from drivers.canopen402 import CanOpen402Bus

    motors = [MotorConfig.rotary(f"m{i}", i, counts_per_rev=4096, gear_ratio=10.0, min_position=-1.0,
                                 max_position=1.0, max_velocity=5.0) for i in range(1, drives + 1)]
    bus = CanOpen402Bus("bench", options, motors)
    bus.open()
    bus.enable()
    try:
        start = {name: s.position for name, s in bus.read().items()}
        waits: list[float] = []
        late = 0
        c0, t0 = cpu_seconds(pid), time.monotonic()
        deadline = t0
        while (now := time.monotonic()) - t0 < seconds:
            offset = 0.05 * math.sin(2.0 * math.pi * (now - t0))
            bus.write({name: pos + offset for name, pos in start.items()})
            w0 = time.perf_counter()
            if not bus.wait_for_feedback(1.0 / rate):
                late += 1
            waits.append(time.perf_counter() - w0)
            bus.read()
            deadline += 1.0 / rate
            time.sleep(max(0.0, deadline - time.monotonic()))
        c1, t1 = cpu_seconds(pid), time.monotonic()
    finally:
        bus.close()
    waits.sort()
    return {"cpu_pct": 100.0 * (c1 - c0) / (t1 - t0), "cycles": len(waits), "feedback_late": late,
            "cpu_ms_per_cycle": 1e3 * (c1 - c0) / max(len(waits), 1),
            "reply_p50_ms": 1e3 * statistics.median(waits), "reply_p99_ms": 1e3 * waits[int(0.99 * (len(waits) - 1))]}


def measure(tree: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One emulator of ``tree``: idle CPU (no client), then driven CPU, and the rate warnings it printed."""
    proc, options = start_emulator(tree, args.drives)
    try:
        time.sleep(1.0)  # boot and imports settle
        c0, t0 = cpu_seconds(proc.pid), time.monotonic()
        time.sleep(args.idle_seconds)
        idle = 100.0 * (cpu_seconds(proc.pid) - c0) / (time.monotonic() - t0)
        result = drive(options, args.drives, args.rate, args.seconds, proc.pid)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    result["idle_cpu_pct"] = idle
    result["rate_warnings"] = [line for line in err.splitlines() if "behind its" in line]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--drives", type=int, default=7, help="CiA 402 drives (the sample head has 7)")
    parser.add_argument("--rate", type=float, default=250.0, help="cycle rate in Hz (the sample head's: 250)")
    parser.add_argument("--seconds", type=float, default=10.0, help="driven seconds per emulator and round")
    parser.add_argument("--idle-seconds", type=float, default=3.0, help="idle seconds per emulator and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--baseline-rev", default=BASELINE_REV, help=f"git revision of the old emulator "
                        f"(default {BASELINE_REV}); 'none' measures only this tree")
    parser.add_argument("--json", type=Path, help="also write the figures and settings here")
    args = parser.parse_args(argv)
    rows: dict[str, list[dict[str, Any]]] = {"current": [], "baseline": []}
    report: dict[str, Any] = {"settings": {k: str(v) for k, v in vars(args).items()},
                              "load_avg_start": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="canopen-baseline-") as tmp:
        trees = {"current": ROOT}
        if args.baseline_rev != "none":
            try:
                report["baseline_commit"] = export_rev(args.baseline_rev, Path(tmp))
                trees["baseline"] = Path(tmp)
            except (subprocess.CalledProcessError, OSError) as exc:
                print(f"baseline {args.baseline_rev} unavailable ({exc}); measuring this tree only")
        for k in range(args.rounds):
            for name, tree in (trees.items() if k % 2 == 0 else reversed(trees.items())):
                try:
                    r = measure(tree, args)
                except Exception as exc:  # a loaded host can stall an emulator past the driver's patience
                    print(f"round {k + 1} {name:<8}: failed ({type(exc).__name__}: {exc}); left out", flush=True)
                    continue
                rows[name].append(r)
                per_drive = r["cpu_pct"] / args.drives
                print(f"round {k + 1} {name:<8}: driven {r['cpu_pct']:5.1f} % of a core ({per_drive:4.1f} % per drive),"
                      f" {r['cpu_ms_per_cycle']:.3f} ms CPU per cycle, idle {r['idle_cpu_pct']:5.1f} %, {r['cycles']} "
                      f"cycles at {args.rate:g} Hz, "
                      f"reply p50 {r['reply_p50_ms']:.2f} ms p99 {r['reply_p99_ms']:.2f} ms, "
                      f"{r['feedback_late']} late, {len(r['rate_warnings'])} rate warnings", flush=True)
    report["load_avg_end"] = os.getloadavg()
    report["rows"] = rows
    if not rows["current"]:
        print("no measurement of the current emulator completed")
        return 1
    cur = statistics.mean(r["cpu_pct"] for r in rows["current"])
    print(f"current emulator: {cur:.1f} % of a core for {args.drives} drives at {args.rate:g} Hz "
          f"({cur / args.drives:.2f} % per drive); load average {report['load_avg_start'][0]:.1f} -> "
          f"{report['load_avg_end'][0]:.1f}")
    if rows["baseline"]:
        old = statistics.mean(r["cpu_pct"] for r in rows["baseline"])
        idle_old = statistics.mean(r["idle_cpu_pct"] for r in rows["baseline"])
        idle_cur = statistics.mean(r["idle_cpu_pct"] for r in rows["current"])
        per_old = statistics.mean(r["cpu_ms_per_cycle"] for r in rows["baseline"])
        per_cur = statistics.mean(r["cpu_ms_per_cycle"] for r in rows["current"])
        report["ratio_driven"] = old / cur
        report["ratio_per_cycle"] = per_old / per_cur
        report["ratio_idle"] = idle_old / max(idle_cur, 1e-9)
        print(f"baseline {args.baseline_rev}: {old:.1f} % driven ({per_old:.3f} ms CPU per cycle), {idle_old:.1f} % "
              f"idle; current {cur:.1f} % ({per_cur:.3f} ms) / {idle_cur:.1f} %: old/new {report['ratio_driven']:.2f}x "
              f"driven, {report['ratio_per_cycle']:.2f}x per cycle, {report['ratio_idle']:.2f}x idle")
    if args.json:
        tmp_path = args.json.with_suffix(".tmp")
        tmp_path.write_text(json.dumps(report, indent=2))
        tmp_path.replace(args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
