"""Tracker sources for calibration and the robust per-pose estimate of each link's pose.

A source returns the next ``n`` capture frames as :class:`~models.capture.MarkerSample` s: a live ZeroMQ capture
stream (``docs/tracker.md``; the simulated tracker runs as a child process serving one). Recorded CSV exports are
replayed through the journal's time windows instead (:mod:`.workflow`).

:func:`estimate` turns one pose's samples into one pose per link: a consensus cluster of positions, widened by
robust sigmas (1.4826·MAD, with floors) in position and then angle, averaged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from models.capture import MarkerSample
from models.errors import LikenessError
from models.rigid import matrix_to_quat, quat_to_matrix, rotation_angle


class CalibrationError(LikenessError):
    """A calibration run cannot go on (no tracker data, hardware fault, plan mismatch...)."""


class TrackerSource(Protocol):
    """Where marker frames come from during a live calibration."""

    description: str

    def collect(self, n_frames: int) -> Sequence[MarkerSample]: ...

    def close(self) -> None: ...


class ZmqSource:
    """A live capture stream: SUB socket on ``endpoint``; ``collect`` returns frames that arrive after the call."""

    def __init__(self, endpoint: str, timeout_s: float = 2.0, skip_frames: int = 1) -> None:
        import zmq

        self.skip_frames = skip_frames
        self.endpoint = endpoint
        self.description = f"zmq://{endpoint}" if "://" in endpoint and not endpoint.startswith("zmq") else endpoint
        self.timeout_s = timeout_s
        self._zmq = zmq
        self._ctx = zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RCVHWM, 10000)
        self._sock.setsockopt(zmq.SUBSCRIBE, b"tracker")
        self._sock.connect(endpoint)

    def collect(self, n_frames: int) -> Sequence[MarkerSample]:
        import msgpack

        from models.capture import unpack_frame

        zmq = self._zmq
        while True:  # drop frames captured before this call (the head was still moving)
            try:
                self._sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
        out: list[MarkerSample] = []
        got = -self.skip_frames  # the first frame may have been captured before the call
        deadline = time.monotonic() + self.timeout_s * max(1, n_frames)
        while got < n_frames:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._sock.poll(int(min(remaining, self.timeout_s) * 1000)):
                raise CalibrationError(f"no tracker frames from {self.endpoint} within {self.timeout_s:.1f} s")
            try:
                frame = unpack_frame(self._sock.recv_multipart())
                if got >= 0:
                    out.extend(frame)
            except (ValueError, KeyError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
                raise CalibrationError(f"bad tracker frame from {self.endpoint}: {exc}") from exc
            got += 1
        return out

    def close(self) -> None:
        self._sock.close(0)


@dataclass
class LinkEstimate:
    """One link's pose at one planned pose: mean of the inlier samples."""

    position: np.ndarray
    quaternion: np.ndarray
    used: int
    rejected: int

    def to_json(self) -> dict:
        return {"p": self.position.tolist(), "q": self.quaternion.tolist(), "n": self.used, "rejected": self.rejected}

    @classmethod
    def from_json(cls, d: dict) -> LinkEstimate:
        return cls(np.asarray(d["p"], dtype=float), np.asarray(d["q"], dtype=float), int(d["n"]), int(d["rejected"]))


def estimate(
    samples: Iterable[MarkerSample],
    links: Sequence[str],
    n_frames: int,
    min_fraction: float = 0.5,
    sigmas: float = 4.0,
    floor_m: float = 0.5e-3,
    floor_rad: float = math.radians(0.5),
) -> dict[str, LinkEstimate]:
    """Robust pose of each link from one pose's samples; links with too few inliers are left out.

    Inliers: the largest cluster of positions within ``2 * floor_m`` of one sample, widened to
    ``sigmas`` robust sigmas (1.4826·MAD) around its median, then filtered the same way by angle.
    """
    by_link: dict[str, list[MarkerSample]] = {name: [] for name in links}
    for s in samples:
        if s.link in by_link:
            by_link[s.link].append(s)
    need = max(2, math.ceil(min_fraction * n_frames))
    out: dict[str, LinkEstimate] = {}
    for name, ss in by_link.items():
        if len(ss) < need:
            continue
        P = np.array([s.position for s in ss], dtype=float)
        Q = np.array([s.quaternion for s in ss], dtype=float)
        Q /= np.linalg.norm(Q, axis=1, keepdims=True)
        # consensus first (RANSAC-like): the sample with most others within 2 floors anchors the inliers, so
        # even half the frames being outliers (e.g. 2 marker swaps among 4 frames) cannot drag the estimate
        dist = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
        near = dist <= 2 * floor_m
        score = near.sum(axis=1) - np.where(near, dist, 0.0).sum(axis=1) / (4 * floor_m * len(P))
        core = near[int(np.argmax(score))]
        med = np.median(P[core], axis=0)
        d = np.linalg.norm(P - med, axis=1)
        keep = d <= max(sigmas * 1.4826 * np.median(d[core]), floor_m)
        R = quat_to_matrix(Q)
        Rm = _mean_rotation(Q[keep]) if keep.any() else _mean_rotation(Q)
        ang = rotation_angle(np.swapaxes(R, 1, 2) @ Rm)
        keep &= ang <= max(sigmas * 1.4826 * np.median(ang), floor_rad)
        if keep.sum() < need:
            continue
        q = matrix_to_quat(_mean_rotation(Q[keep]))
        out[name] = LinkEstimate(P[keep].mean(axis=0), q, int(keep.sum()), int((~keep).sum()))
    return out


def _mean_rotation(Q: np.ndarray) -> np.ndarray:
    """Chordal mean of unit quaternions (signs aligned to the first) as a rotation matrix."""
    Q = np.where((Q @ Q[0])[:, None] < 0, -Q, Q)
    return quat_to_matrix(Q.mean(axis=0))
