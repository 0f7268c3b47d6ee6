"""Resting memory of a daemon: VmRSS of each of its processes with the sample head, before any clip is loaded,
against the goal (<= 120 MiB for the daemon's own process, which runs the control loop) and against a bare
interpreter with numpy and pyzmq measured in the same run (what any Python process of the daemon costs at least).

Starts ``likeness daemon`` (the sample head, emulated buses, free loopback ports) as a child process, waits for its
``ready`` line and ``--rest`` seconds more, then reads ``/proc/PID/status`` of it and every descendant, and from
``/proc/PID/maps`` which heavy native libraries each has mapped (numba's LLVM, onnxruntime, scipy): a mapped library
means the module was imported. With ``--enable`` the head is enabled and holds still first (telemetry then runs the
full strain check of every commanded pose, which must load nothing heavy either).
``python benchmarks/daemon_memory.py [--rest 3] [--config HEAD.toml] [--enable]``.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOAL_MIB = 120.0
#: Native libraries whose mapping shows a heavy import: (what, a path fragment of its shared objects).
HEAVY = (("numba/LLVM", "llvmlite"), ("onnxruntime", "onnxruntime"), ("scipy", "scipy"), ("torch", "torch"),
         ("matplotlib", "matplotlib"))


def vm_rss_mib(pid: int) -> float:
    """VmRSS of a process (MiB)."""
    text = Path(f"/proc/{pid}/status").read_text()
    m = re.search(r"VmRSS:\s+(\d+)\s+kB", text)
    return int(m.group(1)) / 1024 if m else float("nan")


def descendants(pid: int) -> list[int]:
    """``pid`` and every process below it, parents first."""
    out = [pid]
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            kids = [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            continue
        for kid in kids:
            out += descendants(kid)
    return out


def role(pid: int, root: int) -> str:
    """What a process of the daemon is, from its command line."""
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    if pid == root:
        return "daemon (control loop)"
    for key, name in (("runtime.server", "API server"), ("runtime.decoder", "request decoder"),
                      ("sim canopen", "CANopen emulator"), ("sim dynamixel", "Dynamixel emulator"),
                      ("resource_tracker", "resource tracker"), ("spawn_main", "bus process")):
        if key in cmd:
            return name
    return cmd[:60]


def heavy_libraries(pid: int) -> list[str]:
    """Which of :data:`HEAVY` the process has mapped."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return []
    return [name for name, frag in HEAVY if f"/{frag}" in maps]


def bare_interpreter_mib() -> float:
    """VmRSS of ``python -c 'import numpy, zmq'`` at rest, measured now."""
    code = "import numpy, zmq, re, pathlib; t = pathlib.Path('/proc/self/status').read_text(); " \
           "print(int(re.search(r'VmRSS:\\s+(\\d+)', t).group(1)) / 1024)"
    return float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)


def enable(ready_line: str) -> str:
    """Enable the head of the daemon that printed ``ready_line`` (its command endpoint) and move it once; returns
    what state the figures are in."""
    from models.client import Client

    endpoint = re.search(r"commands (\S+),", ready_line)
    if endpoint is None:
        raise RuntimeError(f"no command endpoint in {ready_line!r}")
    with Client(endpoint.group(1), timeout=30) as c:
        c.call("enable")
        c.call("pose", pose={"jaw": 4.0})
        time.sleep(1.0)
        c.call("pose", pose={"jaw": 0.0})
        return f"enabled ({c.call('status')['lifecycle']}), after a pose,"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rest", type=float, default=3.0, help="seconds to wait after the daemon is ready")
    parser.add_argument("--config", type=Path, default=ROOT / "heads" / "sample" / "head.toml")
    parser.add_argument("--enable", action="store_true", help="enable the head before measuring")
    args = parser.parse_args(argv)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    bare = bare_interpreter_mib()
    cmd = [sys.executable, "-m", "likeness", "daemon", "--config", str(args.config), "--command",
           "tcp://127.0.0.1:*", "--telemetry", "tcp://127.0.0.1:*"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=ROOT)
    try:
        assert proc.stdout is not None
        started = time.monotonic()
        for line in proc.stdout:
            if line.startswith("ready"):
                break
        else:
            print(f"the daemon exited with code {proc.wait()} before it was ready")
            return 1
        ready_s = time.monotonic() - started
        state = "resting"
        if args.enable:
            state = enable(line)
        time.sleep(args.rest)
        rows = [(role(pid, proc.pid), pid, vm_rss_mib(pid), heavy_libraries(pid)) for pid in descendants(proc.pid)]
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
    print(f"{state} VmRSS, {args.config.name}, {args.rest:g} s after ready (start took {ready_s:.1f} s); "
          f"bare interpreter with numpy + pyzmq: {bare:.0f} MiB; load average {os.getloadavg()[0]:.1f}")
    for name, pid, rss, libs in rows:
        goal = f"goal <= {GOAL_MIB:.0f} MiB: {'meets' if rss <= GOAL_MIB else 'MISSES'}"
        print(f"  {name:22s} pid {pid:7d}  {rss:6.1f} MiB  x{rss / bare:.2f} bare  {goal}  "
              f"heavy libraries: {', '.join(libs) or 'none'}")
    total = sum(r[2] for r in rows)
    print(f"  all {len(rows)} processes: {total:.0f} MiB (shared pages counted in each)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
