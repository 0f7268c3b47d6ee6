"""The shared e-stop flag carries the latest trip's reason across processes, along with the trip itself."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from runtime.ipc import EStopFlag

ROOT = Path(__file__).resolve().parents[2]


def test_a_trip_in_another_process_is_seen_once_with_its_reason() -> None:
    flag = EStopFlag()
    try:
        assert not flag.tripped() and flag.reason() == "api"
        code = ("import sys; from runtime.ipc import EStopFlag; f = EStopFlag(sys.argv[1]); "
                "f.trip('studio E-stop'); f.close()")
        env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        subprocess.run([sys.executable, "-c", code, flag.name], check=True, timeout=60, env=env)
        assert flag.tripped() and flag.reason() == "studio E-stop"
        assert not flag.tripped()  # once per trip
        flag.trip("é" * 100)  # long, non-ASCII: cut to 63 bytes, a broken last character replaced, never an error
        assert flag.tripped() and flag.reason().startswith("é")
    finally:
        flag.close()
