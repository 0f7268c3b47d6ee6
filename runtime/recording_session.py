"""The API server's open recording: a crash-safe file the core's recorded rows are streamed into.

``record start`` opens a new file under ``[runtime] record_dir`` (never overwriting an earlier one); the core then
hands rows ``[t, commanded..., measured...]`` (SI) over (:class:`runtime.loop_messages.RecordedRows`), written here
in the configured units; ``record stop`` closes it and says how many rows were saved and dropped
(``docs/operations.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.recording import RecordingWriter
from runtime.telemetry import ActuatorUnits


@dataclass
class RecordingSession:
    """One open recording file: its name, writer and the rows written so far."""

    name: str
    writer: RecordingWriter
    rows: int = 0

    @classmethod
    def open(cls, directory: str | Path, name: str, units: ActuatorUnits, meta: dict[str, object]
             ) -> RecordingSession:
        """A new file ``NAME.lrec`` (``NAME-2.lrec``... if taken) in ``directory``."""
        base = Path(directory)
        path = base / f"{name}.lrec"
        k = 1
        while path.exists():  # never overwrite an earlier recording
            k += 1
            path = base / f"{name}-{k}.lrec"
        return cls(name, RecordingWriter(path, list(units.names), list(units.units), meta))

    def append(self, rows: np.ndarray, units: ActuatorUnits) -> None:
        """Rows [t, commanded..., measured...] (SI) → configured units, appended to the file."""
        n = len(units.names)
        block = np.array(rows, dtype=float)
        block[:, 1:1 + n] *= units.inv_scale
        block[:, 1 + n:] *= units.inv_scale
        self.writer.append(block)
        self.rows += len(block)

    def close(self) -> Path:
        """Close the file (complete up to here); its path."""
        self.writer.close()
        return self.writer.path
