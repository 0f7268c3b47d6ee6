"""Request decoding: typed one-pass decode (``runtime.messages.decode_request``) of a 1 MiB ``stream`` request and a
1 MiB ``load_clip`` request, against ``msgpack.unpackb`` of the same bytes (which only builds Python objects and
checks nothing) and against today's path (``msgpack.unpackb`` then the clip parser ``clip_from_dict``), all in this
run. Typed decoding includes every check and the arrays (frames as one float64 array, clip keys per channel): rows
of float64 values are read from the bytes by numpy without Python floats. Untyped ``msgspec.msgpack.decode`` is
printed too, for reference.

Run: ``python benchmarks/decode.py [--repeats 30]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.clip import clip_from_dict
from runtime.messages import decode_request

MIB = 1 << 20


def stream_request(rng: np.random.Generator, channels: int = 52) -> bytes:
    """A ``stream`` request of 52 channels with as many float64 frames as fit in 1 MiB."""
    names = [f"arkit.c{i}" for i in range(channels)]
    frames: list[list[float]] = []
    step = 200
    while True:
        more = [[1000.0 + 0.01 * (len(frames) + k), *rng.uniform(-30, 30, channels).tolist()] for k in range(step)]
        raw = msgpack.packb({"op": "stream", "id": 1, "channels": names, "frames": frames + more})
        if len(raw) > MIB:
            if step == 1:
                return msgpack.packb({"op": "stream", "id": 1, "channels": names, "frames": frames})
            step = max(1, step // 4)
            continue
        frames += more


def clip_request(rng: np.random.Generator, channels: int = 52) -> bytes:
    """A ``load_clip`` request of 52 linear channels, float64 keys, as many as fit in 1 MiB."""
    keys, best = 50, b""
    while True:
        spec = {f"c{c}": {"interp": "linear", "keys": np.column_stack(
            [np.cumsum(rng.uniform(0.01, 0.05, keys)), rng.uniform(-30, 30, keys)]).tolist()}
            for c in range(channels)}
        raw = msgpack.packb({"op": "load_clip", "id": 2, "clip": {"name": "big", "channels": spec}})
        if len(raw) > MIB:
            return best
        best, keys = raw, keys + 50


def best_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(minimum, median) wall time in ms."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times), 1e3 * float(np.median(times))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores", flush=True)
    for label, raw in (("stream", stream_request(rng)), ("load_clip", clip_request(rng))):
        base = best_ms(lambda raw=raw: msgpack.unpackb(raw), args.repeats)
        typed = best_ms(lambda raw=raw: decode_request(raw), args.repeats)
        print(f"{label:<9} {len(raw) / MIB:5.2f} MiB  msgpack.unpackb min {base[0]:6.2f} ms (median {base[1]:6.2f})"
              f"   decode_request min {typed[0]:6.2f} ms (median {typed[1]:6.2f})   ratio x{typed[0] / base[0]:.2f}",
              flush=True)
        plain = best_ms(lambda raw=raw: msgspec.msgpack.decode(raw), args.repeats)
        print(f"{'':<9} for reference, untyped msgspec.msgpack.decode (Python objects, no checks) min "
              f"{plain[0]:6.2f} ms (x{plain[0] / base[0]:.2f})", flush=True)
        if label == "load_clip":
            old = best_ms(lambda raw=raw: clip_from_dict(msgpack.unpackb(raw)["clip"]), max(3, args.repeats // 5))
            print(f"{'':<9} today's unpackb + clip_from_dict min {old[0]:6.2f} ms: typed decode is "
                  f"x{old[0] / typed[0]:.1f} faster", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
