"""Telemetry's full strain check in NumPy (runtime.strain_check): the same measure and verdicts as the sample head's
strain guard (onnxruntime and scipy), and a fresh interpreter that unpickles it, as the API server does from its
start-up spec, and runs it loads neither onnxruntime nor scipy (nor numba or torch)."""

from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.runtime.conftest import SAMPLE

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("onnxruntime", "scipy", "numba", "llvmlite", "torch", "matplotlib")


@pytest.fixture(scope="module")
def guard():
    from models.headspec import load_head
    from models.strain_guard import StrainGuard

    g = StrainGuard.for_head(load_head(SAMPLE))
    assert g is not None
    return g


def _poses(guard, n: int = 12) -> np.ndarray:
    rng = np.random.default_rng(7)
    return guard.lo + rng.uniform(-0.1, 1.1, (n, len(guard.lo))) * (guard.hi - guard.lo)  # some outside the range


def test_numpy_check_agrees_with_the_guard(guard) -> None:
    from runtime.strain_check import FullStrainCheck

    check = FullStrainCheck.of(guard)
    for q in _poses(guard):
        ref = guard.full(q)  # onnxruntime's float32 forward pass, scipy's smoothing
        got = check.full(q)
        assert got == pytest.approx(ref, abs=2e-5), q
        assert check.passes(got) == guard.passes(ref) or min(abs(np.subtract(got, guard.strain_range))) < 1e-4
        assert check.in_range(q) == guard.in_range(q)
        assert check.check(q) == guard.check(q)


def test_server_side_check_loads_no_heavy_library(guard, tmp_path: Path) -> None:
    from runtime.strain_check import FullStrainCheck

    blob = tmp_path / "check.pickle"
    blob.write_bytes(pickle.dumps(FullStrainCheck.of(guard)))
    q = _poses(guard, 1)[0]
    code = f"""
import pickle, sys
import numpy as np
import runtime.server  # what the API server process imports
from models.headspec import load_head
from runtime.telemetry import ActuatorUnits, Telemetry
check = pickle.loads(open({str(blob)!r}, "rb").read())
head = load_head({str(SAMPLE)!r})
tel = Telemetry(None, head, ActuatorUnits.of(head), check)
out = tel._confirm_guard(0.0, np.array({q.tolist()!r}))
tel.close()
print(repr(out["strain"]))
print("heavy:" + ",".join(sorted(m for m in {HEAVY!r} if m in sys.modules)))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr
    strain_line, heavy_line = res.stdout.strip().splitlines()[-2:]
    assert heavy_line == "heavy:", f"the server's telemetry loaded {heavy_line}"
    assert eval(strain_line) == pytest.approx([round(x, 4) for x in guard.full(q)], abs=2e-4)
