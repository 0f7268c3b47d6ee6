"""Helpers for the runtime benchmarks: a daemon on the sample head (emulated buses) or with no bus at all."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SAMPLE = ROOT / "heads" / "sample" / "head.toml"
logging.basicConfig(level=logging.ERROR)  # emulators under load log retries; the numbers tell the story


#: The emulated buses' patience, raised (heartbeat, transfers, missed replies): a loaded host, or emulators demoted
#: below the daemon (:func:`demote_emulators`), stalls the emulated devices for seconds, and a bus fault would end a
#: measurement of a path that does not depend on them (real buses keep the head file's values).
PATIENT = (("timeout_s = 1.0    # emulated drives", "timeout_s = 5.0    # emulated drives"),
           ("feedback_timeout_s = 1.0\n", "feedback_timeout_s = 5.0\n"), ("sdo_timeout_s = 1.0", "sdo_timeout_s = 5.0"),
           ("max_consecutive_failures = 20", "max_consecutive_failures = 500"), ("retries = 8", "retries = 10"))


def patient_head(out: Path, fragment: str = "[inputs]\n") -> Path:
    """The sample head written to ``out`` (file references made absolute) with :data:`PATIENT` buses and the
    ``[inputs]`` tables of ``fragment``."""
    from runtime.inputs.headfile import head_with_inputs

    frag = out.parent / "inputs.toml"
    out.parent.mkdir(parents=True, exist_ok=True)
    frag.write_text(fragment)
    path = head_with_inputs(SAMPLE, frag, out)
    text = path.read_text()
    for old, new in PATIENT:
        if old not in text:
            raise RuntimeError(f"the sample head no longer has {old!r}: update benchmarks/_daemon.PATIENT")
        text = text.replace(old, new)
    path.write_text(text)
    return path


def make_daemon(rate_hz: float, realtime: bool, with_buses: bool = True, head_path: Path | None = None,
                **extra: Any) -> Any:
    """A started, enabled daemon on free loopback ports; ``with_buses=False`` runs the loop without bus I/O."""
    from models.headspec import load_head
    from runtime.daemon import Daemon
    from runtime.hardware import Hardware

    head = load_head(SAMPLE if head_path is None else head_path)
    overrides = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                 "runtime.rate_hz": rate_hz, "runtime.realtime": realtime, "runtime.telemetry_hz": min(50, rate_hz),
                 "safety.feedback_timeout_s": 0.5, **extra}
    hardware = None if with_buses else Hardware(head, {})
    daemon = Daemon(head, overrides, hardware=hardware)
    daemon.start()
    daemon.enable()
    return daemon


@contextlib.contextmanager
def performance_daemon(rate_hz: float, performance: Path, extra: dict[str, Any] | None = None,
                       record_inputs: bool = False) -> Any:
    """The daemon on the sample head (emulated buses) at ``rate_hz``, enabled, with the clip of ``performance``
    loaded and half a second to settle: yields (daemon, client, the load reply); stopped on exit."""
    from models.client import Client
    from models.clip import clip_file_as_dict
    from models.headspec import load_head
    from runtime.daemon import Daemon

    clip = clip_file_as_dict(performance)
    overrides = {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                 "runtime.rate_hz": rate_hz, "runtime.telemetry_hz": 50.0, **(extra or {})}
    daemon = Daemon(load_head(SAMPLE), overrides, record_inputs=record_inputs)
    daemon.start()
    try:
        with Client(daemon.command_endpoint, timeout=30) as c:
            c.call("enable")
            reply = c.call("load_clip", clip=clip)
            time.sleep(0.5)
            yield daemon, c, reply
    finally:
        daemon.stop()


def add_settings(parser: Any) -> None:
    """The ``--set TABLE.KEY=VALUE`` option of the latency benchmarks (read it with :func:`settings`)."""
    parser.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                        help="a daemon config override, e.g. runtime.api_priority=5 (TOML value); repeatable")


def settings(args: Any) -> dict[str, Any]:
    """The ``--set`` overrides as a dict of config keys to values."""
    import tomllib

    return {k: tomllib.loads(f"v = {v}")["v"] for k, v in (item.split("=", 1) for item in args.set)}


def add_emulator_nice(parser: Any) -> None:
    """The ``--emulator-nice`` option of the latency benchmarks (read it with :func:`demote_emulators`)."""
    parser.add_argument("--emulator-nice", type=int, default=None,
                        help="niceness of the emulator processes (default: the daemon's); e.g. 10 to measure the "
                             "daemon's own path with the emulated devices taking only the CPU it leaves")


def demote_emulators(nice: int | None) -> str:
    """Start emulator processes at niceness ``nice`` (added to this process's) instead of the daemon's default
    (``runtime.simhw.EMULATOR_NICE``); returns a line for the report. A positive value stands in for hardware whose
    CPU is not the host's: the emulators then take what the daemon's processes leave."""
    from runtime import simhw

    if nice is None:
        return f"emulators at niceness {simhw.EMULATOR_NICE:+d} (the daemon's default)"
    simhw.EMULATOR_NICE = nice
    return f"emulators demoted to niceness {nice:+d} (standing in for devices with CPUs of their own)"


#: SCHED_FIFO priority of a benchmark's steady sender: above the daemon's helper processes and the emulators, below
#: the control loop (80).
SENDER_PRIORITY = 10


def external_sender() -> str:
    """Make the calling process a stand-in for a show-control machine of its own: SCHED_FIFO at
    ``SENDER_PRIORITY`` (call it first, before any ZeroMQ context exists, so the context's I/O thread inherits it).
    On a shared 2-core host a normal-priority sender queues behind the emulators (niceness −10) and sends its
    frames milliseconds off its grid, which is this host's load, not the network a real sender's frames cross.
    Returns a line for the report."""
    import os

    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(SENDER_PRIORITY))
    except (AttributeError, OSError) as exc:
        return f"sender at normal priority ({type(exc).__name__}: SCHED_FIFO not permitted)"
    return f"sender SCHED_FIFO {SENDER_PRIORITY}"


#: SCHED_FIFO priority of the benchmark's own watcher (the thread that polls the bus link in the daemon's process):
#: the lowest realtime priority, below every thread of the daemon and the senders.
WATCHER_PRIORITY = 1


class Watching:
    """While the calling thread polls a bus link in the daemon's process (the loop thread's process): SCHED_FIFO at
    :data:`WATCHER_PRIORITY` where permitted, normal scheduling again after. At normal priority on a busy host the
    watcher is preempted while it holds the GIL, and the control loop then waits for the GIL until the watcher runs
    again: a stall of the benchmark's making (a daemon's own process runs no such thread). Under SCHED_FIFO nothing
    of normal priority preempts it, and it sleeps between polls, so it takes little CPU from anything else."""

    def __enter__(self) -> Watching:
        import os

        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(WATCHER_PRIORITY))
        return self

    def __exit__(self, *exc: object) -> None:
        import os

        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def sleep_until(t: float) -> None:
    """Sleep until monotonic time ``t``, spinning only the last 100 µs (a realtime sender wakes within tens of µs)."""
    import time

    while (left := t - time.monotonic()) > 0:
        time.sleep(left - 100e-6 if left > 150e-6 else 0)


def run_sender_watching_jaw(daemon: Any, target: Any, args: tuple, what: str) -> tuple[Any, Any, Any]:
    """Run ``target(*args, queue)`` in a process of its own (a steady sender that puts its result on the queue) while
    polling the bus link that carries the jaw; returns (write times, jaw targets written, the sender's result)."""
    import multiprocessing as mp
    import time

    import numpy as np

    link = next(lk for lk in daemon.buses if "jaw" in lk.actuators)
    j = link.actuators.index("jaw")
    writes: list[tuple[float, float]] = [(0.0, float("nan"))]  # (bus write time, jaw target) from the bus process
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, out), daemon=True)
    proc.start()
    got: Any = None
    with Watching():
        while got is None:
            fb = link.feedback()
            if fb.write_stamp != writes[-1][0]:
                writes.append((fb.write_stamp, float(fb.written[j])))
            try:
                got = out.get_nowait()
            except Exception:
                time.sleep(200e-6)
            if not proc.is_alive() and got is None and out.empty():
                raise RuntimeError(f"the {what} process ended without a result (exit code {proc.exitcode})")
    proc.join(5)
    return np.array([w[0] for w in writes]), np.array([w[1] for w in writes]), got


def first_moves(stamps: Any, values: Any, times: Any, with_times: bool = False) -> list[Any]:
    """For each step time, the delay (s) to the first bus write after it that moved the jaw (with ``with_times``:
    (step time, delay) pairs); steps that came while the jaw was still moving cannot be timed and are left out."""
    import numpy as np

    lat: list[Any] = []
    for t in times:
        i = int(np.searchsorted(stamps, t))  # first write after the step
        if i < 2 or i >= len(stamps) or values[i - 1] != values[i - 2]:
            continue
        moved = np.nonzero(values[i:] != values[i - 1])[0]
        if len(moved):
            delay = float(stamps[i + moved[0]] - t)
            lat.append((float(t), delay) if with_times else delay)
    return lat


def pct(values: Any, q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else float("nan")


def cpu_steal_s() -> float:
    """Seconds of CPU time the hypervisor has taken from this machine's CPUs since boot (``/proc/stat``'s steal, all
    CPUs together; NaN where unknown): the difference over a run is time the machine could not run at all, which
    shows as missed deadlines and latency tails no software on it can avoid."""
    import math
    import os

    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK") if fields[0] == "cpu" and len(fields) > 8 else math.nan
    except (OSError, ValueError):
        return math.nan
