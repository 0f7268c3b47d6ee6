"""Phase lock of the control loop to a steady stream: cycles slide to just after the frames reach the daemon.

A fixed-rate loop samples a stream at an arbitrary phase, so a frame waits up to one period for its cycle (at
250 Hz, 0–4 ms). When frames arrive at a steady phase of the loop (a producer at the loop rate, or at a divisor of
it), the lock moves the loop's deadlines by a small bounded step per cycle until cycles fall ``lead`` seconds after
the arrivals (the API server's receipt stamps, which the loop's own schedule does not move): the frame then waits
only for the hand-over to the loop, not for the period. The loop's rate never changes on
average; a single period changes by at most ``max_step`` (a few percent, inside the shaper's velocity margin and the
drivers' rate tolerance). Arrivals that do not keep a steady phase (bursty clients, a producer whose rate is not a
divisor of the loop's) are detected by the spread of their phases and leave the loop alone.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass


@dataclass
class PhaseLock:
    """Tracks arrival phases and proposes a deadline correction per cycle (pure: no clock, no I/O).

    ``period``: loop period (s); ``lead``: wanted time from an arrival to the cycle that takes it (s); ``gain``:
    fraction of the phase error corrected per arrival; ``max_step``: largest correction per cycle as a fraction of
    the period; ``coherence``: how tightly the arrival phases must cluster (0–1, length of their mean phasor)
    before the lock acts; ``alpha``: weight of the newest arrival in that mean."""

    period: float
    lead: float = 500e-6
    gain: float = 0.2
    max_step: float = 0.03
    coherence: float = 0.8
    alpha: float = 0.05
    _mean: complex = 0j
    _shift: float = 0.0  # total correction applied, so phases are judged on the loop's original grid
    _pending: float | None = None  # phase error of the latest arrival not yet corrected
    _n: int = 0
    last_error: float | None = None  # the latest arrival's distance from the wanted phase (s)

    def arrival(self, received: float, deadline: float) -> None:
        """A frame that arrived at ``received`` is taken by the cycle due at ``deadline``."""
        x = _wrap(deadline - received - self.lead, self.period)
        raw = _wrap(x - self._shift, self.period)
        self._mean = (1 - self.alpha) * self._mean + self.alpha * cmath.exp(2j * math.pi * raw / self.period)
        self._n += 1
        self._pending = self.last_error = x

    @property
    def locked(self) -> bool:
        """True once enough arrivals kept a steady phase for the lock to act."""
        return self._n * self.alpha >= 1.0 and abs(self._mean) >= self.coherence

    def correction(self) -> float:
        """Seconds to add to the next deadline (negative: earlier), 0 when unlocked; consumes the latest error."""
        x, self._pending = self._pending, None
        if x is None or not self.locked:
            return 0.0
        limit = self.max_step * self.period
        step = max(-limit, min(limit, -self.gain * x))
        self._shift += step
        return step


def _wrap(x: float, period: float) -> float:
    """``x`` folded into [-period/2, period/2)."""
    return (x + period / 2) % period - period / 2
