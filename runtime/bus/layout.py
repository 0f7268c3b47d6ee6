"""The block of shared memory between the loop side and one bus process, and the vocabulary encoded in it.

Layout: eight int64 counters; two feedback buffers (a float64 header, then positions, velocities and the last
written targets, ``n`` each); two target buffers (the targets' stamp, then ``n`` targets); a fault block (a 4-byte
length and a JSON map). Each double buffer is guarded by a pair of counters: the writer bumps ``begun``, writes the
buffer of that parity, then sets ``done``; a reader copies the buffer of ``done``'s parity and keeps the copy if
``begun`` has not moved two further. Nothing is pickled and nothing is locked, so either side takes microseconds.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from drivers.base import LifecycleState

#: Connection states of a bus as its process reports them: not opened yet or stopped, open and reachable, lost (waiting
#: for the next reconnect attempt), a reconnect attempt in progress.
ConnectionState = Literal["closed", "connected", "lost", "reconnecting"]
CONNECTION_STATES: tuple[ConnectionState, ...] = get_args(ConnectionState)
CONNECTION_CODE: dict[ConnectionState, int] = {s: i for i, s in enumerate(CONNECTION_STATES)}

LIFECYCLE_STATES: tuple[LifecycleState, ...] = tuple(LifecycleState)
LIFECYCLE_CODE: dict[LifecycleState, int] = {s: i for i, s in enumerate(LIFECYCLE_STATES)}

# counters (int64): feedback begun/done, targets begun/done, faults begun/done
C_FB_BEGUN, C_FB_DONE, C_TG_BEGUN, C_TG_DONE, C_FA_BEGUN, C_FA_DONE = range(6)
N_COUNTERS = 8
# feedback header (float64), then positions, velocities, written (n each)
H_SEQ, H_STAMP, H_WSTAMP, H_IO_US, H_STATE, H_CONNECTED, H_FAULTS, H_CONNECTION, H_ATTEMPTS, H_RETRY_AT = range(10)
N_HEADER = 10
FAULT_BYTES = 8192

#: Active faults by device: (code, message).
Faults = dict[str, tuple[int, str]]


@dataclass(frozen=True, slots=True)
class Views:
    """numpy views onto one shared block: counters, the two feedback buffers, the two target buffers, faults."""

    counters: np.ndarray
    feedback: tuple[np.ndarray, np.ndarray]
    targets: tuple[np.ndarray, np.ndarray]
    faults: np.ndarray


@dataclass(frozen=True, slots=True)
class Layout:
    """Offsets and sizes of the shared block for ``n`` actuators."""

    n: int

    @property
    def fb_len(self) -> int:
        """float64 values per feedback buffer."""
        return N_HEADER + 3 * self.n

    @property
    def tg_len(self) -> int:
        """float64 values per target buffer (stamp, then targets)."""
        return 1 + self.n

    @property
    def off_fb(self) -> int:
        """Byte offset of the first feedback buffer."""
        return N_COUNTERS * 8

    @property
    def off_tg(self) -> int:
        """Byte offset of the first target buffer."""
        return self.off_fb + 2 * self.fb_len * 8

    @property
    def off_fa(self) -> int:
        """Byte offset of the fault block."""
        return self.off_tg + 2 * self.tg_len * 8

    @property
    def size(self) -> int:
        """Bytes of the whole block."""
        return self.off_fa + FAULT_BYTES

    def views(self, buf: memoryview) -> Views:
        """Views onto ``buf`` (a :class:`multiprocessing.shared_memory.SharedMemory`'s ``buf``)."""
        fb, tg = self.fb_len, self.tg_len
        return Views(
            counters=np.ndarray((N_COUNTERS,), np.int64, buf, 0),
            feedback=(np.ndarray((fb,), np.float64, buf, self.off_fb),
                      np.ndarray((fb,), np.float64, buf, self.off_fb + fb * 8)),
            targets=(np.ndarray((tg,), np.float64, buf, self.off_tg),
                     np.ndarray((tg,), np.float64, buf, self.off_tg + tg * 8)),
            faults=np.ndarray((FAULT_BYTES,), np.uint8, buf, self.off_fa),
        )

    def initialize(self, views: Views) -> None:
        """A fresh block: no reads, no targets, no faults, the bus unconfigured and closed."""
        views.counters[:] = 0
        for buf in views.feedback:
            buf[:] = np.nan
            buf[H_SEQ] = 0
            buf[H_STATE] = LIFECYCLE_CODE[LifecycleState.UNCONFIGURED]
            buf[H_CONNECTED] = 0
            buf[H_FAULTS] = 0
            buf[H_CONNECTION] = CONNECTION_CODE["closed"]
            buf[H_ATTEMPTS] = 0
            buf[H_RETRY_AT] = np.inf
        for buf in views.targets:
            buf[:] = np.nan


def write_faults(views: Views, faults: Faults, version: int) -> None:
    """Publish ``faults`` as fault version ``version`` (messages cut to 300 characters, devices dropped to fit)."""
    data = {k: [int(v[0]), str(v[1])[:300]] for k, v in faults.items()}
    raw = json.dumps(data).encode()
    while len(raw) > FAULT_BYTES - 4 and data:
        data.popitem()
        raw = json.dumps(data).encode()
    views.counters[C_FA_BEGUN] = version
    views.faults[:4] = np.frombuffer(len(raw).to_bytes(4, "little"), np.uint8)
    views.faults[4:4 + len(raw)] = np.frombuffer(raw, np.uint8)
    views.counters[C_FA_DONE] = version


def read_faults(views: Views) -> tuple[int, Faults] | None:
    """(version, faults) of a consistent copy of the fault block, or None if it kept changing under the reader."""
    c = views.counters
    for _ in range(3):
        done = int(c[C_FA_DONE])
        raw = views.faults.tobytes()
        if int(c[C_FA_BEGUN]) == done:
            size = int.from_bytes(raw[:4], "little")
            try:
                data = json.loads(raw[4:4 + size]) if size else {}
            except ValueError:
                continue
            return done, {k: (int(v[0]), str(v[1])) for k, v in data.items()}
    return None
