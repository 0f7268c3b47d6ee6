"""The recording stage: while recording, every cycle's time, command and measured positions as one row.

Rows are handed out with the outputs every telemetry period (the API server writes the file), so the core only ever
holds a few periods of them. :class:`RecorderState` keeps the recording's name, the rows not yet handed out and the
counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models import errors as E
from runtime.core import commands as C
from runtime.core.cycle import CycleOutputs
from runtime.core.events import Body, RecordStarted, RecordStopped
from runtime.core.params import CoreParams


@dataclass
class RecorderState:
    """The recording under way (None: not recording), its rows not yet handed out, its start and its size."""

    name: str | None = None
    rows: np.ndarray | None = None
    count: int = 0  # rows in ``rows`` not yet handed out
    total: int = 0
    t0: float = 0.0


def on_record(rec: RecorderState, params: CoreParams, out: CycleOutputs, t: float, cmd: C.Record) -> Body:
    """Start or stop recording."""
    if cmd.action == "start":
        if rec.name is not None:
            raise E.BadState(f"already recording {rec.name!r}")
        n = len(params.names)
        if rec.rows is None:
            # rows are handed out every telemetry period, so a few periods of rows is all the core ever holds
            rec.rows = np.empty((8 * params.telemetry_every + 8, 1 + 2 * n))
        rec.name = cmd.name
        rec.count = rec.total = 0
        rec.t0 = t
        out.emit(RecordStarted(t, cmd.name))
        return {"recording": cmd.name}
    if rec.name is None:
        raise E.BadState("not recording")
    name, rec.name = rec.name, None
    flush(rec, out)
    out.emit(RecordStopped(t, name, rec.total))
    return {"recording": name, "samples": rec.total, "stopped": True}


def record(rec: RecorderState, params: CoreParams, out: CycleOutputs, t: float, commanded: np.ndarray,
           measured: np.ndarray) -> None:
    """This cycle's row (up to the recording's capacity); rows go out every telemetry period."""
    if rec.name is None or rec.rows is None:
        return
    if rec.total >= params.record_capacity:
        return
    rows = rec.rows
    if rec.count >= rows.shape[0]:
        flush(rec, out)
    n = len(params.names)
    row = rows[rec.count]
    row[0] = t - rec.t0
    row[1:1 + n] = commanded
    row[1 + n:] = measured
    rec.count += 1
    rec.total += 1
    if rec.count >= params.telemetry_every:
        flush(rec, out)


def flush(rec: RecorderState, out: CycleOutputs) -> None:
    """Hand the rows held out."""
    if rec.rows is None or not rec.count:
        return
    block = rec.rows[:rec.count].copy()
    out.record = block if out.record is None else np.vstack([out.record, block])
    rec.count = 0
