"""The calibration journal: an append-only JSON-lines file that makes runs resumable.

The first record names the plan (its digest), head and actuators; then one record per recorded pose (commanded
and measured actuator values, the tracker time window, each link's estimated pose) and one for limit
discovery. Each line is flushed and fsynced; a torn last line (a crash mid-write) is ignored on reading.
A resumed run skips every pose already in the journal and refuses a journal written for another plan.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from offline.calibration.capture import CalibrationError


class Journal:
    """Append records to ``path``; :meth:`load` returns what an earlier run recorded."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.header: dict[str, Any] | None = None
        self.poses: dict[int, dict[str, Any]] = {}
        self.discovery: dict[str, Any] | None = None
        self._fh = None

    def load(self) -> Journal:
        """Read an existing journal (if any)."""
        if not self.path.exists():
            return self
        lines = self.path.read_text(encoding="utf-8").split("\n")
        for i, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as exc:
                if i >= len(lines) - 1:  # torn last line from an interrupted write
                    break
                raise CalibrationError(f"{self.path}: line {i}: not valid JSON: {exc}") from exc
            kind = rec.get("type")
            if kind == "header":
                self.header = rec
            elif kind == "pose":
                self.poses[int(rec["index"])] = rec
            elif kind == "discovery":
                self.discovery = rec
            else:
                raise CalibrationError(f"{self.path}: line {i}: unknown record type {kind!r}")
        return self

    def start(self, header: dict[str, Any]) -> None:
        """Open for appending; write ``header`` for a new journal or check it matches the existing one."""
        if self.header is not None:
            for key in ("plan", "head", "actuators"):
                if self.header.get(key) != header.get(key):
                    raise CalibrationError(
                        f"{self.path}: the journal was written for a different {key} "
                        f"({self.header.get(key)!r}, now {header.get(key)!r}); use a new --out directory"
                    )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # drop a torn last line before appending
        if self.path.exists():
            text = self.path.read_text(encoding="utf-8")
            if text and not text.endswith("\n"):
                keep = text[: text.rfind("\n") + 1]
                self.path.write_text(keep, encoding="utf-8")
        self._fh = self.path.open("a", encoding="utf-8")
        if self.header is None:
            self.header = {"type": "header", **header}
            self._write(self.header)

    def append(self, record: dict[str, Any]) -> None:
        self._write(record)
        if record["type"] == "pose":
            self.poses[int(record["index"])] = record
        elif record["type"] == "discovery":
            self.discovery = record

    def _write(self, record: dict[str, Any]) -> None:
        assert self._fh is not None, "journal not started"
        self._fh.write(json.dumps(record, allow_nan=False) + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
