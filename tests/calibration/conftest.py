"""Shared fixtures: the sample head, its mechanism, the simulated tracker read in-process, a daemon of the bare
mechanism."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.headspec import load_head
from sim_hardware.mechanism import sample_mechanism

SAMPLE = Path(__file__).resolve().parents[2] / "heads" / "sample" / "head.toml"


class SimSource:
    """A calibration tracker source reading ``sim_hardware.tracker.SimTracker`` in-process (no network)."""

    def __init__(self, tracker) -> None:
        self.tracker = tracker
        self.description = "sim"

    def collect(self, n_frames: int):
        return self.tracker.capture(n_frames)

    def close(self) -> None:
        pass


@pytest.fixture(scope="session")
def sample_head():
    return load_head(SAMPLE)


@pytest.fixture(scope="session")
def sample_mech(sample_head):
    return sample_mechanism(sample_head, seed=5)


def start_bare_daemon(head, tmp_path, data=None):
    """An in-process daemon of ``head`` (or of its config ``data``, a TOML map) without its skin predictor (as
    ``likeness calibrate`` runs it: the bare mechanism, no skin-strain guard) on free loopback ports; started again
    if the emulated buses do not answer."""
    import tomllib

    from drivers.errors import BusError
    from models.headspec import head_from_dict
    from runtime.daemon import Daemon

    data = tomllib.loads(Path(head.source).read_text()) if data is None else data
    for key in ("predictor", "predictor_optional", "skin_guard"):
        data.get("paths", {}).pop(key, None)
    bare = head_from_dict(data, source=head.source)
    for attempt in range(3):  # emulated buses may not answer in time on a saturated shared CPU: start again
        d = Daemon(bare, {"api.command": "tcp://127.0.0.1:*", "api.telemetry": "tcp://127.0.0.1:*",
                          "runtime.record_dir": str(tmp_path / "rec"), "runtime.realtime": False,
                          "runtime.rate_hz": 100.0})
        try:
            d.start()
            return d
        except BusError:
            d.stop()
            if attempt == 2:
                raise
    raise AssertionError("unreachable")
