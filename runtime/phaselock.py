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
    before the lock acts; ``release``: how far that length must fall before an engaged lock lets go (hysteresis:
    a few frames a loaded host delivers late do not drop it); ``alpha``: weight of the newest arrival in that mean.
    While engaged, an arrival more than a quarter period off where the arrivals cluster (a straggler) moves no
    deadline and does not count in the mean; more than ``1 / alpha`` of them in a row (the stream moved) and the lock
    lets go and starts afresh.

    ``slotted``: a frame runs its cycle as soon as it is taken once its period slot (the period before ``deadline``)
    has begun (the runner's wake on input). Deadlines one period apart then differ: a frame a period before its
    deadline waits for its slot, one less than a period before runs at once. So the error is not folded modulo the
    period (a lock that put the slot's start just after the frames pulls it back before them); only the clustering
    of phases is."""

    period: float
    lead: float = 500e-6
    gain: float = 0.2
    max_step: float = 0.03
    coherence: float = 0.8
    release: float = 0.5
    alpha: float = 0.05
    slotted: bool = False
    _engaged: bool = False
    _stragglers: int = 0  # stragglers in a row while engaged
    _mean: complex = 0j
    _shift: float = 0.0  # total correction applied, so phases are judged on the loop's original grid
    _pending: float | None = None  # phase error of the latest arrival not yet corrected
    _n: int = 0
    last_error: float | None = None  # the latest arrival's distance from the wanted phase (s)

    def arrival(self, received: float, deadline: float) -> None:
        """A frame that arrived at ``received`` is taken by the cycle due at ``deadline``."""
        x = deadline - received - self.lead
        if not self.slotted:
            x = _wrap(x, self.period)
        raw = _wrap(x - self._shift, self.period)
        self.last_error = x
        center = cmath.phase(self._mean) / (2 * math.pi) * self.period  # where the arrivals cluster
        if self._engaged and abs(_wrap(raw - center, self.period)) > 0.25 * self.period:
            # a straggler: it moves nothing; a run of them means the stream moved, and the lock starts afresh
            self._pending = None
            self._stragglers += 1
            if self._stragglers * self.alpha > 1.0:
                self._engaged, self._mean, self._n, self._stragglers = False, 0j, 0, 0
            return
        self._stragglers = 0
        self._mean = (1 - self.alpha) * self._mean + self.alpha * cmath.exp(2j * math.pi * raw / self.period)
        self._n += 1
        c = abs(self._mean)
        self._engaged = self._n * self.alpha >= 1.0 and c >= (self.release if self._engaged else self.coherence)
        self._pending = x

    @property
    def locked(self) -> bool:
        """True once enough arrivals kept a steady phase for the lock to act (until their phases scatter)."""
        return self._engaged

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
