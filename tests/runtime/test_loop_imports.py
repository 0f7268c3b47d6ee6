"""The daemon's own process (the control loop's) at rest imports neither numba's compiler nor onnxruntime, nor the
training, plotting or offline libraries: its in-cycle kernels come from the module compiled ahead of time
(``models.kernels_aot``) and its predictor opens no session (the loop runs on the weights), so it rests at a fraction
of the memory (``benchmarks/daemon_memory.py`` prints the figure)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from models.kernel_support import kernels_available

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "heads" / "sample" / "head.toml"
#: Top-level modules the loop process must not import.
CUT = ("numba", "llvmlite", "onnxruntime", "torch", "matplotlib", "sklearn", "offline", "studio", "sim_hardware")

_SCRIPT = """
import json, sys
from models.headspec import load_head
from runtime.daemon import Daemon
from runtime.hardware import Hardware
head = load_head(sys.argv[1])
daemon = Daemon(head, {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                       "runtime.realtime": False}, hardware=Hardware(head, {}))
daemon.start()
try:
    solvers = [type(s).__name__ for s in daemon.target_solvers]
    print(json.dumps({"modules": sorted({m.split(".")[0] for m in sys.modules}), "solvers": solvers,
                      "lifecycle": daemon.lifecycle}))
finally:
    daemon.stop()
"""


@pytest.mark.skipif(not kernels_available(), reason="numba is not installed: the loop runs the numpy kernels")
def test_resting_loop_process_imports_no_compiler_and_no_offline_libraries() -> None:
    from models.kernels import warm
    from models.kernels_aot import module

    warm(str(SAMPLE))  # builds the ahead-of-time kernels where `make install` has not (minutes, once)
    assert module() is not None, "the ahead-of-time kernels were not built"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", _SCRIPT, str(SAMPLE)], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert "SkinTargetSolver" in got["solvers"]  # the loop did build the skin solve it runs every cycle
    imported = set(got["modules"])
    assert "numpy" in imported and "runtime" in imported
    assert not imported & set(CUT), f"the loop process imported {sorted(imported & set(CUT))}"
