"""Where an input's time goes on its way to the bus: a ring of stamps the loop runner writes for each live value and
stream frame it takes.

Per command: when the daemon received it (the server's stamp, ``received``), when the loop took it off the command
pipe, when the cycle that first applied it woke, and when that cycle had posted its targets to the bus processes.
With the sender's own send time and the bus process's write stamp (``BusFeedback.write_stamp``) a benchmark splits
packet → bus write into its stages (``benchmarks/input_latency.py``). Writing a row is a few float stores into a
preallocated array: nothing is allocated in the loop thread.
"""

from __future__ import annotations

import numpy as np

#: Rows kept (the oldest are overwritten).
TRACE_ROWS = 1024
#: Columns of a row.
RECEIVED, TAKEN, WOKE, POSTED = range(4)


class InputTrace:
    """The last :data:`TRACE_ROWS` commands' stamps (time.monotonic(), NaN: not yet); :attr:`count` rows written."""

    def __init__(self, rows: int = TRACE_ROWS) -> None:
        self.rows = np.full((rows, 4), np.nan)
        self.count = 0
        self.open_rows = 0  # rows taken and not yet applied by a cycle (the last ``_open`` rows written)

    def taken(self, received: float | None, at: float) -> None:
        """A live value or stream frame received at ``received`` (None: unknown) left the pipe at ``at``."""
        row = self.rows[self.count % len(self.rows)]
        row[RECEIVED] = np.nan if received is None else received
        row[TAKEN] = at
        row[WOKE] = row[POSTED] = np.nan
        self.count += 1
        self.open_rows = min(self.open_rows + 1, len(self.rows))

    def applied(self, woke: float, posted: float) -> None:
        """The cycle that woke at ``woke`` and posted its targets at ``posted`` applied every open row."""
        n = len(self.rows)
        for k in range(self.count - self.open_rows, self.count):
            row = self.rows[k % n]
            row[WOKE] = woke
            row[POSTED] = posted
        self.open_rows = 0

    def last(self, k: int = 1) -> np.ndarray:
        """The last ``k`` rows written, oldest first (a copy)."""
        k = min(k, self.count, len(self.rows))
        idx = [(self.count - k + i) % len(self.rows) for i in range(k)]
        return self.rows[idx].copy()
