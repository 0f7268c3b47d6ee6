"""A simulated marker tracker and the capture formats it shares with real systems.

A capture system reports, per frame, one marker frame (rigid body) per tracked link: a timestamp, the
link name, a position in metres and an orientation quaternion. :class:`SimTracker` produces such frames
from the virtual mechanism's ground truth with Gaussian noise, dropouts (a link missing from a frame) and
outliers (a marker swap: a jump of centimetres and a wrong orientation) at settable rates.

Formats (see ``docs/tracker.md``):
- CSV export, one row per marker per frame: ``time,link,x,y,z,qw,qx,qy,qz`` (seconds, metres, unit quaternion).
- ZeroMQ stream: a PUB socket sending two-part messages ``[b"tracker", msgpack(frame)]`` where
  ``frame = {"v": 1, "time": t, "frame": i, "markers": {link: [x, y, z, qw, qx, qy, qz]}}``.
"""

from __future__ import annotations

import csv
import io
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.errors import SpecError
from models.linkmap import write_atomic
from models.rigid import matrix_to_quat, quat_to_matrix, rotvec_to_matrix

CSV_COLUMNS = ("time", "link", "x", "y", "z", "qw", "qx", "qy", "qz")
TOPIC = b"tracker"
STREAM_VERSION = 1


@dataclass(frozen=True)
class MarkerSample:
    """One tracked marker frame: capture time (s), link name, position (m), quaternion (w, x, y, z)."""

    time: float
    link: str
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]


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
        mechanism,
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


# ---------------------------------------------------------------------------- CSV export / replay
def samples_to_csv(samples: Iterable[MarkerSample]) -> str:
    """CSV text with a header row and one row per marker sample."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for s in samples:
        w.writerow([f"{s.time:.6f}", s.link, *(f"{v:.7f}" for v in s.position), *(f"{v:.8f}" for v in s.quaternion)])
    return buf.getvalue()


def write_csv(path: str | Path, samples: Iterable[MarkerSample]) -> Path:
    """Write samples as a capture export CSV, atomically."""
    path = Path(path)
    write_atomic(path, samples_to_csv(samples))
    return path


class CsvAppender:
    """Append samples to a capture CSV as they arrive (the header is written once)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._fh = self.path.open("a", encoding="utf-8", newline="")
        if new:
            self._fh.write(",".join(CSV_COLUMNS) + "\n")

    def write(self, samples: Iterable[MarkerSample]) -> None:
        text = samples_to_csv(samples)
        self._fh.write(text.split("\n", 1)[1])
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def read_csv(path: str | Path) -> list[MarkerSample]:
    """Read a capture export; errors name the file, row and column."""
    path = Path(path)
    src = str(path)
    try:
        fh = path.open(encoding="utf-8", newline="")
    except OSError as exc:
        raise SpecError(src, "file", f"cannot read capture CSV: {exc.strerror or exc}") from exc
    out: list[MarkerSample] = []
    with fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or [h.strip().lower() for h in header] != list(CSV_COLUMNS):
            raise SpecError(src, "header", f"expected columns {','.join(CSV_COLUMNS)}", header)
        for i, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(CSV_COLUMNS):
                raise SpecError(src, f"row {i}", f"expected {len(CSV_COLUMNS)} columns, got {len(row)}", row)
            try:
                vals = [float(row[0]), *(float(v) for v in row[2:])]
            except ValueError as exc:
                raise SpecError(src, f"row {i}", f"not a number: {exc}", row) from exc
            if not all(math.isfinite(v) for v in vals):
                raise SpecError(src, f"row {i}", "values must be finite", row)
            q = vals[4:]
            if math.sqrt(sum(v * v for v in q)) < 1e-6:
                raise SpecError(src, f"row {i} (qw..qz)", "quaternion has zero length", q)
            if not row[1]:
                raise SpecError(src, f"row {i} (link)", "empty link name")
            out.append(MarkerSample(vals[0], row[1], tuple(vals[1:4]), tuple(q)))
    return out


class CaptureLog:
    """Recorded samples indexed by time, for replaying the windows a calibration journal names."""

    def __init__(self, samples: Sequence[MarkerSample]) -> None:
        self.samples = sorted(samples, key=lambda s: s.time)
        self._times = np.array([s.time for s in self.samples])

    def between(self, t0: float, t1: float) -> list[MarkerSample]:
        """Samples with ``t0 <= time <= t1`` (1 µs tolerance for rounding in exports)."""
        i = int(np.searchsorted(self._times, t0 - 1e-6, side="left"))
        j = int(np.searchsorted(self._times, t1 + 1e-6, side="right"))
        return self.samples[i:j]


# ---------------------------------------------------------------------------- ZeroMQ stream
def pack_frame(frame_index: int, samples: Sequence[MarkerSample]) -> list[bytes]:
    """The two-part ZeroMQ message of one capture frame."""
    import msgpack

    t = samples[0].time if samples else time.time()
    body = {
        "v": STREAM_VERSION,
        "time": t,
        "frame": frame_index,
        "markers": {s.link: [*s.position, *s.quaternion] for s in samples},
    }
    return [TOPIC, msgpack.packb(body, use_bin_type=True)]


def unpack_frame(parts: Sequence[bytes]) -> list[MarkerSample]:
    """Marker samples of one received frame; ``ValueError`` naming what is wrong on a bad message."""
    import msgpack

    if len(parts) != 2 or parts[0] != TOPIC:
        raise ValueError("expected a two-part message [b'tracker', msgpack frame]")
    body = msgpack.unpackb(parts[1], raw=False)
    if not isinstance(body, dict) or body.get("v") != STREAM_VERSION:
        raise ValueError(f"unsupported tracker frame (v={body.get('v') if isinstance(body, dict) else None!r})")
    t = float(body["time"])
    out = []
    for link, vals in dict(body.get("markers", {})).items():
        if not isinstance(vals, (list, tuple)) or len(vals) != 7:
            raise ValueError(f"marker {link!r}: expected [x, y, z, qw, qx, qy, qz]")
        v = [float(x) for x in vals]
        out.append(MarkerSample(t, str(link), tuple(v[:3]), tuple(v[3:])))
    return out


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
