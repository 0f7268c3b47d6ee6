"""A MIDI timecode generator: quarter frames at the real pace over any mido output port (a TCP MIDI port from
``mido.sockets.connect``, or a MIDI port). It stands in for a show's timecode master in the examples, the tests and
the benchmark: ``roll(seconds)`` runs from a timecode, ``halt()`` stops sending, ``locate(seconds)`` sends a full
frame. The timecode follows the generator's clock, so a stalled thread skips frames instead of drifting."""

from __future__ import annotations

import threading
import time
from typing import Any

from runtime.inputs.config import RATES
from runtime.inputs.mtc import frame_of, full_frame, quarter_frames


class MtcGenerator:
    """Sends MTC on ``port`` from a thread of its own until :meth:`close`."""

    def __init__(self, port: Any, rate: str = "25") -> None:
        if rate not in RATES:
            raise ValueError(f"rate must be one of {', '.join(RATES)}")
        self.port = port
        self.rate = rate
        self.running = False
        self.tc0 = 0.0
        self.t0 = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mtc-generator", daemon=True)
        self._thread.start()

    def position(self) -> float | None:
        """The timecode now (seconds), None while halted."""
        with self._lock:
            return self.tc0 + (time.monotonic() - self.t0) if self.running else None

    def roll(self, seconds: float) -> None:
        """Run from timecode ``seconds`` (now)."""
        with self._lock:
            self.tc0, self.t0, self.running = seconds, time.monotonic(), True

    def halt(self) -> None:
        with self._lock:
            self.running = False

    def locate(self, seconds: float) -> None:
        """Stop and send a full-frame message at ``seconds``."""
        self.halt()
        with self._lock:
            self.port.send(full_frame(frame_of(seconds, self.rate), self.rate))

    def _run(self) -> None:
        fps = RATES[self.rate]
        quarter = 1.0 / fps / 4
        while not self._stop.is_set():
            tc = self.position()
            if tc is None:
                time.sleep(0.005)
                continue
            frame = frame_of(tc, self.rate) // 2 * 2  # a sequence starts on an even frame
            start = time.monotonic() - (tc - frame / fps)
            for k, msg in enumerate(quarter_frames(frame, self.rate)):
                delay = start + k * quarter - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                with self._lock:
                    if not self.running or self._stop.is_set():
                        break
                    self.port.send(msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.port.close()
