"""The shared e-stop flag carries the latest trip's reason across processes, along with the trip itself."""

from __future__ import annotations

import multiprocessing as mp

from runtime.ipc import EStopFlag


def _trip(name: str, reason: str) -> None:
    flag = EStopFlag(name)
    flag.trip(reason)
    flag.close()


def test_a_trip_in_another_process_is_seen_once_with_its_reason() -> None:
    flag = EStopFlag()
    try:
        assert not flag.tripped() and flag.reason() == "api"
        p = mp.get_context("spawn").Process(target=_trip, args=(flag.name, "studio E-stop"))
        p.start()
        p.join(30)
        assert p.exitcode == 0
        assert flag.tripped() and flag.reason() == "studio E-stop"
        assert not flag.tripped()  # once per trip
        flag.trip("é" * 100)  # long, non-ASCII: truncated to whole characters or replaced, never an error
        assert flag.tripped() and flag.reason().startswith("é")
    finally:
        flag.close()
