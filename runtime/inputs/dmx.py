"""DMX slots → channel values, and the merge of several sACN sources of one universe (pure; no sockets).

E1.31 merge: only the sources of the highest priority count; among them, each slot takes the highest value (HTP) or
the value of the source that changed that slot last (LTP). A source silent for ``timeout`` seconds leaves the merge
(E1.31's network data loss), so a lower-priority backup takes over.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from runtime.inputs.config import DMX_SLOTS, SlotMap


class SlotDecoder:
    """Decodes a 512-slot universe into the mapped channels' values (config units)."""

    def __init__(self, slots: Sequence[SlotMap]) -> None:
        self.channels = tuple(s.channel for s in slots)
        self.coarse = np.array([s.index for s in slots], dtype=np.intp)
        self.fine = np.array([s.index + 1 if s.bits == 16 else -1 for s in slots], dtype=np.intp)
        sixteen = self.fine >= 0
        self.full = np.where(sixteen, 65535.0, 255.0)
        self.lo = np.array([s.lo for s in slots])
        self.span = np.array([s.hi - s.lo for s in slots])
        self._sixteen = sixteen

    def decode(self, dmx: np.ndarray) -> np.ndarray:
        """``dmx`` (512 slot values 0-255) → one value per mapped channel: DMX 0 → lo, full → hi, linear."""
        raw = dmx[self.coarse].astype(float)
        if self._sixteen.any():
            fine = dmx[np.where(self._sixteen, self.fine, 0)].astype(float)
            raw = np.where(self._sixteen, raw * 256.0 + fine, raw)
        return self.lo + self.span * (raw / self.full)


@dataclass
class SourceData:
    """One sACN source's latest universe."""

    priority: int
    dmx: np.ndarray
    seen: float  # when its last packet arrived
    changed: np.ndarray  # when each slot last changed (LTP)
    name: str = ""
    sequence: int = -1


@dataclass
class Merger:
    """Latest universe of every source (by CID) and their merge."""

    mode: str = "htp"  # "htp" | "ltp"
    timeout: float = 2.5
    sources: dict[bytes, SourceData] = field(default_factory=dict)

    def update(self, cid: bytes, priority: int, dmx: Sequence[int], now: float, name: str = "",
               sequence: int | None = None) -> tuple[bool, bool]:
        """Take one packet; returns (accepted, new source). A packet out of sequence (E1.31: up to 20 behind the
        last) is dropped."""
        data = np.zeros(DMX_SLOTS, dtype=np.uint8)
        data[:min(len(dmx), DMX_SLOTS)] = np.asarray(dmx[:DMX_SLOTS], dtype=np.uint8)
        src = self.sources.get(cid)
        if src is not None and sequence is not None and src.sequence >= 0:
            diff = (sequence - src.sequence) % 256
            if diff == 0 or diff > 236:  # within 20 behind: out of order
                return False, False
        if src is None:
            self.sources[cid] = SourceData(priority, data, now, np.full(DMX_SLOTS, now), name,
                                           -1 if sequence is None else sequence)
            return True, True
        moved = src.dmx != data
        if moved.any():
            src.changed[moved] = now
            src.dmx = data
        src.priority, src.seen, src.name = priority, now, name
        if sequence is not None:
            src.sequence = sequence
        return True, False

    def expire(self, now: float) -> list[str]:
        """Drop the sources silent for longer than the timeout; returns their names."""
        gone = [cid for cid, s in self.sources.items() if now - s.seen > self.timeout]
        return [self.sources.pop(cid).name or cid.hex() for cid in gone]

    def terminate(self, cid: bytes) -> None:
        """A source said it stops (E1.31 stream terminated)."""
        self.sources.pop(cid, None)

    def merged(self) -> np.ndarray | None:
        """The merged universe, None without any source."""
        if not self.sources:
            return None
        top = max(s.priority for s in self.sources.values())
        winners = [s for s in self.sources.values() if s.priority == top]
        if len(winners) == 1:
            return winners[0].dmx.copy()
        if self.mode == "htp":
            return np.max(np.stack([s.dmx for s in winners]), axis=0)
        changed = np.stack([s.changed for s in winners])
        last = np.argmax(changed, axis=0)
        return np.stack([s.dmx for s in winners])[last, np.arange(DMX_SLOTS)]
