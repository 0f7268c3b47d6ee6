"""Clips as the core plays them: a clip's curves bound to indices of the head's channel vector.

The API server builds a :class:`BoundClip` (validation and compilation happen there, off the control path); the core
only calls :meth:`BoundClip.sample_into` once per cycle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from runtime.core.channels import ChannelMap
from runtime.curves import Clip


@dataclass(frozen=True)
class BoundClip:
    """A compiled clip plus the channel-vector index of each of its channels."""

    name: str
    duration: float
    channel_names: tuple[str, ...]
    channels: np.ndarray  # channel-vector index per clip channel
    compiled: Any  # has sample(t, out) writing one value per clip channel
    nbytes: int
    key_count: int
    scratch: np.ndarray

    def sample_into(self, t: float, values: np.ndarray) -> None:
        """Write the clip's channel values at clip time ``t`` into the channel vector ``values``."""
        self.compiled.sample(t, self.scratch)
        values[self.channels] = self.scratch


def bind_clip(clip: Clip, channels: ChannelMap) -> BoundClip:
    """Compile ``clip`` to arrays and bind it to the head's channel vector (UnknownChannel for a foreign channel)."""
    names = tuple(clip.channels)
    idx = channels.indices(names)
    compiled = _compile(clip, names)
    nbytes = int(getattr(compiled, "nbytes", 0)) or _nbytes(compiled)
    return BoundClip(clip.name, clip.duration, names, idx, compiled, nbytes, clip.key_count(),
                     np.empty(len(names)))


class _CurveSampler:
    """Samples a clip's curves one by one (used when no array compiler is available)."""

    def __init__(self, clip: Clip, names: tuple[str, ...]) -> None:
        self._curves = [clip.channels[n] for n in names]
        self.nbytes = 64 * clip.key_count()

    def sample(self, t: float, out: np.ndarray) -> None:
        for k, curve in enumerate(self._curves):
            out[k] = curve.value(t)


def _compile(clip: Clip, names: tuple[str, ...]) -> Any:
    try:
        from runtime.compiled import compile_clip
    except ImportError:
        return _CurveSampler(clip, names)
    return compile_clip(clip, names)


def _nbytes(obj: Any) -> int:
    return sum(v.nbytes for v in vars(obj).values() if isinstance(v, np.ndarray)) if hasattr(obj, "__dict__") else 0
