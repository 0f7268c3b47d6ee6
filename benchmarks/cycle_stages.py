"""Where a control cycle's time goes: each stage of the cycle timed in the running daemon (the sample head on emulated
buses, playing a performance) and, as the baseline measured in the same run, the same stages replayed back to back
on the inputs the loop recorded (warm caches, nothing else waking in between).

Stages: the runner's reading of the buses' feedback and the command pipe (``inputs``), the core's
:func:`~runtime.core.core.control` and its parts (read, supervise, watch, sources, solve, guard, shape), the post to the
bus processes (``write``), the recording and telemetry after it (``report``) and the messages to the API server
(``outbox``). The ratio loop / replay per stage is what the running loop pays for its caches being cold and its two
cores shared. Each stage is timed by a wrapper around its function (about 1 µs each, in both columns).

Run: ``python benchmarks/cycle_stages.py [--rate 500] [--performance heads/sample/performances/expressive.json]``,
with nothing else running (on 2 cores a busy second core doubles timings).
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

try:
    from benchmarks._daemon import ROOT, SAMPLE, add_settings, performance_daemon, settings
except ImportError:  # run as a script
    from _daemon import ROOT, SAMPLE, add_settings, performance_daemon, settings

#: (label, module, attribute): the core's stage functions, timed where they are looked up (module attributes).
CORE_STAGES = (("read", "runtime.core.buses", "read"), ("supervise", "runtime.core.lifecycle", "supervise"),
               ("watch: feedback age", "runtime.core.watch", "check_feedback"),
               ("watch: following error", "runtime.core.watch", "check_following"),
               ("sources", "runtime.core.sources", "sample"), ("solve", "runtime.core.solve", "to_targets"),
               ("guard", "runtime.core.guard", "guarded"), ("shape", "runtime.core.shape", "shape"))
#: The runner's own steps (methods of runtime.runner.Runner) and the core's two halves.
RUNNER_STAGES = (("inputs", "_inputs"), ("write", "_write"), ("report", "_report"), ("outbox", "_outbox"))


class Timings:
    """Per stage, the durations of the calls made on the thread being measured (the control thread, then the
    replay's)."""

    def __init__(self) -> None:
        self.thread = "likeness-control"
        self.rows: dict[str, list[float]] = {}
        self.on = False

    def wrap(self, label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        self.rows[label] = []
        rows = self.rows[label]

        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.on or threading.current_thread().name != self.thread:
                return fn(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                rows.append(time.perf_counter() - t0)

        return timed

    def take(self) -> dict[str, np.ndarray]:
        out = {k: np.array(v) * 1e6 for k, v in self.rows.items()}
        for v in self.rows.values():
            v.clear()
        return out


def install(tm: Timings) -> None:
    """Wrap the stages (before the daemon is built, so every caller looks the wrappers up)."""
    import importlib

    from runtime import runner
    from runtime.core import core

    for label, module, name in CORE_STAGES:
        mod = importlib.import_module(module)
        setattr(mod, name, tm.wrap(label, getattr(mod, name)))
    core.control = tm.wrap("control (all of the core's stages)", core.control)
    for label, name in RUNNER_STAGES:
        setattr(runner.Runner, name, tm.wrap(label, getattr(runner.Runner, name)))


def run_loop(tm: Timings, rate_hz: float, performance: Path,
             extra: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], Any, list, dict]:
    """The daemon playing ``performance`` (``extra``: config overrides): the stages' timings over the play, the
    daemon, its recorded inputs and the loop's statistics."""
    with performance_daemon(rate_hz, performance, extra, record_inputs=True) as (daemon, c, reply):
        assert daemon.input_log is not None and daemon.runner is not None
        first = len(daemon.input_log)
        tm.on = True
        c.call("play", clip=reply["clip"])
        time.sleep(reply["duration"])
        tm.on = False
        stats = daemon.runner.stats.summary()
        last = len(daemon.input_log)
    return tm.take(), daemon, daemon.input_log[:last], {"first": first, **stats}


def replay(tm: Timings, daemon: Any, head_inputs: list, first: int) -> dict[str, np.ndarray]:
    """The recorded inputs through a fresh core, back to back on this thread: the core's stages warm."""
    from models.headspec import load_head
    from runtime.core import core as K
    from runtime.core.state import CoreState

    head = load_head(SAMPLE)
    state = CoreState.initial(head, daemon.params, daemon.target_solvers)
    tm.thread = threading.current_thread().name
    for k, inputs in enumerate(head_inputs):
        tm.on = k >= first and not inputs.between_cycles
        out = K.control(state, daemon.params, inputs)
        if not inputs.between_cycles:
            K.report(state, daemon.params, out, inputs.t)
    tm.on = False
    return tm.take()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rate", type=float, default=500.0)
    parser.add_argument("--performance", type=Path,
                        default=ROOT / "heads" / "sample" / "performances" / "expressive.json")
    add_settings(parser)
    args = parser.parse_args(argv)
    tm = Timings()
    install(tm)
    load0 = os.getloadavg()[0]
    loop, daemon, inputs, stats = run_loop(tm, args.rate, args.performance, settings(args))
    warm = replay(tm, daemon, inputs, stats["first"])
    print(f"cycle stages, sample head at {args.rate:g} Hz playing {args.performance.name}: {stats.get('cycles', 0)} "
          f"cycles, {stats.get('missed', 0)} missed, work p50 {stats.get('work_p50_us', float('nan')):.0f} µs; "
          f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")
    print(f"  {'stage':<36} {'loop p50':>9} {'p90':>7} {'p99':>7}   {'replay p50':>10} {'p99':>7}   loop/replay p50")
    for label, a in loop.items():
        if not len(a):
            continue
        b = warm.get(label, np.zeros(0))
        p = np.percentile(a, [50, 90, 99])
        if len(b):
            q = np.percentile(b, [50, 99])
            ratio = f"x{p[0] / q[0]:.1f}" if q[0] > 0 else "-"
            cells = f"{q[0]:10.1f} {q[1]:7.1f}   {ratio}"
        else:
            cells = f"{'(runner)':>10} {'':>7}   -"
        print(f"  {label:<36} {p[0]:9.1f} {p[1]:7.1f} {p[2]:7.1f}   {cells}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
