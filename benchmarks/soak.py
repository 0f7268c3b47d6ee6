"""Soak under faults: the sample head at 500 Hz on emulated hardware for ``--minutes`` (default 10), streaming a
performance from one client and taking OSC cues from another while it records, with a fault injected every
``--interval`` seconds (default 30) in turn: the CAN bus killed and restarted, a drive's heartbeat stopped, a servo
overloaded, a burst of malformed requests, clients that connect and vanish. The soak's operator client recovers each
fault as ``docs/operations.md`` says (remove the cause, ``reset``, ``enable``).

It reports, against the goals: deadlines missed outside fault handling (goal 0; a fault's handling runs from its
injection to 2 s after the head is active again), each fault detected and recovered (time to the daemon's fault,
time from removing the cause to the head active again), frames recorded against control cycles and stream frames
accepted against sent while active (goal: none lost), and the VmRSS of the daemon's processes (the daemon and its
children, not the emulators) after the warm-up and at the end (goal: growth <= 10 MiB). Beside the daemon bare
realtime loops at its rate and priority, one pinned to each CPU (``benchmarks/_soak_sentinel.py``), count the
deadlines the machine itself took away (a loop with no work misses one only when its CPU ran no top-priority thread
for a whole period), and the report says how many of the daemon's misses came with one of those; each of those
loops also times a fixed piece of interpreter work at every wake-up, and the report counts the wake-ups where it ran
several times slower than its median (a CPU running slowly, which a sleeping loop does not see) and how many of the
daemon's misses came with one of those or a miss. It writes
``report.json`` (figures and settings), ``timeline.png``, the daemon's log and the recording into ``--out``.

Run: ``python benchmarks/soak.py [--minutes 10] [--interval 30] [--rate 500] [--out out/soak]``
(``nice -n 5`` on a shared machine: the daemon's control thread runs SCHED_FIFO regardless).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import _daemon as D  # noqa: E402
from benchmarks import _soak_clients as SC  # noqa: E402
from benchmarks import _soak_report as SR  # noqa: E402
from benchmarks._soak_faults import FaultRun, Operator  # noqa: E402
from benchmarks._soak_sentinel import SLOW_FACTOR, Sentinel  # noqa: E402

SAMPLE = ROOT / "heads" / "sample" / "head.toml"
PERFORMANCE = ROOT / "heads" / "sample" / "performances" / "expressive.json"
FAULTS = ("can_bus_killed", "heartbeat_stopped", "servo_overloaded", "malformed_burst", "client_vanished")
WARMUP_S = 10.0
#: Where in each fault slot (fractions of ``--interval``) the fault comes and the OSC cue sender drives.
INJECT_AT, OSC_FROM, OSC_TO = 0.1, 0.7, 0.85
SETTLE_S = 2.0  # a fault's handling ends this long after the head is active again
START_TIMEOUT_S = 240.0  # a cold start on a loaded 2-core machine takes about a minute


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_daemon(out: Path, rate: float, osc_port: int) -> tuple[subprocess.Popen[bytes], str, str]:
    """``likeness daemon`` on the sample head with an OSC input, recording into ``out``; returns it and its
    command and telemetry endpoints once it answers ``status``."""
    from models.client import Client

    inputs = out / "osc.toml"
    inputs.write_text(f'[inputs.osc]\nbind = "127.0.0.1:{osc_port}"\n\n[inputs.osc.map]\n'
                      '"/face/jaw" = "jaw"\n"/face/blink" = "blink"\n')
    command, telemetry = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    log = (out / "daemon.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "likeness", "daemon", "--config", str(SAMPLE), "--rate", str(rate),
                             "--command", command, "--telemetry", telemetry, "--inputs", str(inputs),
                             "--set", f'runtime.record_dir="{out}"'], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    end = time.monotonic() + START_TIMEOUT_S
    with Client(command, timeout=1.0) as c:
        while time.monotonic() < end:
            if proc.poll() is not None:
                raise RuntimeError(f"the daemon exited ({proc.returncode}): see {out / 'daemon.log'}")
            try:
                if c.request("status", timeout=1.0).get("ok"):
                    return proc, command, telemetry
            except TimeoutError:
                continue
    proc.kill()
    raise RuntimeError(f"the daemon did not answer in {START_TIMEOUT_S:g} s: see {out / 'daemon.log'}")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def run_soak(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """Start everything, run the fault slots, stop everything; returns the report."""
    from models.clip import load_clip_file

    clip = load_clip_file(PERFORMANCE)
    osc_port = free_port()
    daemon, command, telemetry = start_daemon(out, args.rate, osc_port)
    collector = SC.Collector(telemetry)
    collector.start()
    operator = Operator(command, collector, daemon.pid, out)
    t0 = time.monotonic()
    interval = args.interval

    def in_osc_window(t: float) -> bool:
        if t < WARMUP_S:
            return False
        phase = ((t - WARMUP_S) % interval) / interval
        return OSC_FROM <= phase < OSC_TO

    from runtime.config import RuntimeSettings

    sentinel = Sentinel(args.rate, RuntimeSettings().priority).start()  # the daemon's rate and loop priority
    streamer = SC.Streamer(command, clip, args.stream_hz, t0, in_osc_window, collector.active)
    osc = SC.OscSender(osc_port, args.osc_hz, t0, in_osc_window)
    runs: list[FaultRun] = []
    memory: list[tuple[float, float]] = []
    report: dict[str, Any] = {}
    try:
        c = operator.client
        if (run := operator.recover_unexpected()) is not None:  # a starved emulator missed a heartbeat on the way up
            runs.append(run)
        start_up = FaultRun("start-up", "enable at start", time.monotonic(), False)
        operator.recover(start_up)
        if start_up.t_recovered is None:
            raise RuntimeError(f"the head could not be enabled: {start_up.notes}")
        streamer.start()
        osc.start()
        def sleep_until(t: float) -> None:
            _sleep_until(t, daemon, memory, operator, runs)

        sleep_until(t0 + WARMUP_S)
        report["memory_start"] = SC.daemon_memory(daemon.pid)
        report["record_start"] = c.call("record", action="start", name="soak")
        report["cycles_start"] = c.call("status")["loop"]["cycles"]
        end = t0 + args.minutes * 60.0
        slot = 0
        while (start := t0 + WARMUP_S + slot * interval) + interval <= end + 1e-6:
            sleep_until(start + INJECT_AT * interval)
            if (pending := operator.recover_unexpected(ask=True)) is not None:  # the head must be active to fault
                runs.append(pending)
            name = args.faults[slot % len(args.faults)]
            run = getattr(operator, name)()
            runs.append(run)
            print(f"  {run.summary()}", flush=True)
            slot += 1
        sleep_until(max(end, time.monotonic()))
        report["record_stop"] = c.call("record", action="stop")
        report["cycles_stop"] = c.call("status")["loop"]["cycles"]
        report["memory_end"] = SC.daemon_memory(daemon.pid)
        report["status_end"] = c.call("status")
    finally:
        for th in (streamer, osc):
            th.stop_event.set()
        for th in (streamer, osc):
            if th.is_alive():
                th.join(5)
        operator.client.request("disable")
        operator.close()
        daemon.send_signal(signal.SIGINT)
        try:
            daemon.wait(30)
        except subprocess.TimeoutExpired:
            daemon.kill()
        collector.stop_event.set()
        collector.join(5)
        sentinel_misses = sentinel.stop()
    report.update(t0=t0, runs=runs, memory=memory, streamer=streamer.counts, osc_sent=osc.sent,
                  collector=collector, daemon_rc=daemon.returncode,
                  sentinel={"scheduling": sentinel.scheduling, "misses": sentinel_misses, "slow": sentinel.slow,
                            "probe_median": sentinel.probe_median, "slow_factor": SLOW_FACTOR})
    return report


def _sleep_until(t: float, daemon: subprocess.Popen[bytes], memory: list[tuple[float, float]], operator: Operator,
                 runs: list[FaultRun]) -> None:
    """Wait until ``t``, sampling the daemon's memory every 5 s and recovering a fault nobody injected; stop at once
    if the daemon died."""
    while (left := t - time.monotonic()) > 0:
        if daemon.poll() is not None:
            raise RuntimeError(f"the daemon exited with {daemon.returncode} during the soak")
        if (run := operator.recover_unexpected()) is not None:
            runs.append(run)
            print(f"  {run.summary()}", flush=True)
            continue
        if not memory or time.monotonic() - memory[-1][0] >= 5.0:
            memory.append((time.monotonic(), SC.daemon_memory(daemon.pid)["total"]))
        time.sleep(min(left, 0.5))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--interval", type=float, default=30.0, help="seconds between faults (default 30)")
    parser.add_argument("--rate", type=float, default=500.0, help="control loop rate in Hz (default 500)")
    parser.add_argument("--stream-hz", type=float, default=100.0, help="performance frames per second")
    parser.add_argument("--osc-hz", type=float, default=25.0, help="OSC cue updates per second in its windows")
    parser.add_argument("--faults", default=",".join(FAULTS), help=f"faults in turn (default {','.join(FAULTS)})")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "soak", help="report folder (default out/soak)")
    args = parser.parse_args(argv)
    args.faults = [f.strip() for f in args.faults.split(",") if f.strip()]
    unknown = sorted(set(args.faults) - set(FAULTS))
    if unknown or not args.faults:
        parser.error(f"--faults: unknown {unknown}; known: {', '.join(FAULTS)}")
    if args.interval < 10 or args.minutes * 60.0 < WARMUP_S + args.interval:
        parser.error(f"--interval must be >= 10 s and --minutes must leave {WARMUP_S:g} s of warm-up plus one "
                     "interval")
    args.out.mkdir(parents=True, exist_ok=True)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    settings.update(head=str(SAMPLE.relative_to(ROOT)), head_sha256=sha256(SAMPLE),
                    performance=str(PERFORMANCE.relative_to(ROOT)), performance_sha256=sha256(PERFORMANCE),
                    warmup_s=WARMUP_S, settle_s=SETTLE_S, load_avg_start=os.getloadavg(), cpus=os.cpu_count(),
                    commit=subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                          text=True).stdout.strip())
    print(f"soak: {args.minutes:g} min at {args.rate:g} Hz, a fault every {args.interval:g} s "
          f"({', '.join(args.faults)}); output in {args.out}", flush=True)
    steal0 = D.cpu_steal_s()
    raw = run_soak(args, args.out)
    settings["load_avg_end"] = os.getloadavg()
    settings["hypervisor_steal_s"] = D.cpu_steal_s() - steal0  # CPU time no process here could run
    result = SR.summarize(raw, settings, SETTLE_S)
    SR.write_timeline(raw, result, args.out / "timeline.png")
    path = args.out / "report.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=str))
    tmp.replace(path)
    SR.print_summary(result, path)
    return 0 if result["goals_met"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
