"""A simulated marker tracker for the virtual mechanism, and its ZeroMQ publisher.

:class:`SimTracker` reports the mechanism's ground-truth link poses as a capture system would (one marker frame
per link per capture frame, ``models.capture.MarkerSample``) with Gaussian noise, dropouts (a link missing from
a frame) and outliers (a marker swap: a jump of centimetres and a wrong orientation) at settable rates.
:class:`TrackerPublisher` serves it as a live capture stream in the documented format (``docs/tracker.md``).
The capture formats themselves live in :mod:`models.capture`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from models.capture import MarkerSample, pack_frame
from models.mechanism import Mechanism
from models.rigid import matrix_to_quat, quat_to_matrix, rotvec_to_matrix


@dataclass
class TrackerNoise:
    """Error model: per-axis position noise (m), rotation noise (rad, per axis of a small rotation vector),
    per-marker dropout and outlier probabilities, and the outlier jump size (m)."""

    position_sigma: float = 0.2e-3
    rotation_sigma: float = math.radians(0.2)
    dropout_rate: float = 0.02
    outlier_rate: float = 0.01
    outlier_jump: float = 0.02


class SimTracker:
    """Marker frames of a virtual mechanism: ``positions()`` gives the motors' true SI positions.

    ``capture(n)`` returns the next ``n`` frames. With ``realtime=False`` (fast tests) frame times advance
    at ``rate_hz`` from the clock without sleeping; with ``realtime=True`` each frame is taken when due.
    """

    def __init__(
        self,
        mechanism: Mechanism,
        positions: Callable[[], Mapping[str, float]],
        noise: TrackerNoise | None = None,
        rate_hz: float = 120.0,
        seed: int = 0,
        links: Sequence[str] | None = None,
        clock: Callable[[], float] = time.time,
        realtime: bool = False,
    ) -> None:
        self.mechanism = mechanism
        self.positions = positions
        self.noise = noise or TrackerNoise()
        self.rate_hz = float(rate_hz)
        self.rng = np.random.default_rng(seed)
        self.links = tuple(links) if links is not None else tuple(mechanism.links)
        self.clock = clock
        self.realtime = realtime
        self._next_time = -math.inf
        self._truth_key: tuple | None = None
        self._truth: tuple[np.ndarray, np.ndarray] | None = None
        self._lock = threading.Lock()

    def frame(self, t: float) -> list[MarkerSample]:
        """One capture frame at time ``t`` of the mechanism as it is now."""
        positions = dict(self.positions())
        key = tuple(sorted(positions.items()))
        if key != self._truth_key:  # the mechanism is static between moves: reuse its poses
            truth = self.mechanism.link_poses(positions)
            self._truth = (
                np.array([truth[k][:3, 3] for k in self.links]),
                np.array([truth[k][:3, :3] for k in self.links]),
            )
            self._truth_key = key
        t_true, R_true = self._truth
        n = self.noise
        m = len(self.links)
        rng = self.rng
        p = t_true + rng.normal(0.0, n.position_sigma, (m, 3))
        R = rotvec_to_matrix(rng.normal(0.0, n.rotation_sigma, (m, 3))) @ R_true
        dropped = rng.random(m) < n.dropout_rate
        outlier = rng.random(m) < n.outlier_rate
        if outlier.any():
            k = int(outlier.sum())
            d = rng.normal(size=(k, 3))
            p[outlier] += n.outlier_jump * d / np.linalg.norm(d, axis=1, keepdims=True)
            R[outlier] = rotvec_to_matrix(rng.normal(0.0, 0.3, (k, 3))) @ R[outlier]
        q = matrix_to_quat(R)
        return [
            MarkerSample(t, link, (float(p[i, 0]), float(p[i, 1]), float(p[i, 2])), tuple(float(v) for v in q[i]))
            for i, link in enumerate(self.links)
            if not dropped[i]
        ]

    def capture(self, n_frames: int) -> list[MarkerSample]:
        """The next ``n_frames`` frames (all markers of each)."""
        dt = 1.0 / self.rate_hz
        samples: list[MarkerSample] = []
        with self._lock:
            t = max(self.clock(), self._next_time)  # frames are periodic from here on
            for _ in range(n_frames):
                if self.realtime:
                    delay = t - self.clock()
                    if delay > 0:
                        time.sleep(delay)
                samples.extend(self.frame(round(t, 6)))
                t += dt
            self._next_time = t
        return samples


# ---------------------------------------------------------------------------- ZeroMQ stream
class TrackerPublisher:
    """Publish a :class:`SimTracker` as a live ZeroMQ capture stream (a background thread at its rate)."""

    def __init__(self, tracker: SimTracker, endpoint: str = "tcp://127.0.0.1:*") -> None:
        import zmq

        self.tracker = tracker
        self._ctx = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.PUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.bind(endpoint)
        self.endpoint = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-tracker", daemon=True)
        self.frames = 0
        self._thread.start()

    def _run(self) -> None:
        dt = 1.0 / self.tracker.rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            samples = self.tracker.capture(1)
            self._sock.send_multipart(pack_frame(self.frames, samples))
            self.frames += 1
            next_t += dt
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close(0)


def rotation_matrix(sample: MarkerSample) -> np.ndarray:
    """The sample's orientation as a rotation matrix."""
    return quat_to_matrix(np.asarray(sample.quaternion))
