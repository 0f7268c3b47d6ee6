"""Clips as the core plays them: a clip's curves bound to indices of the head's channel vector.

The API server builds a :class:`BoundClip` (validation and compilation happen there, off the control path); the core
only calls :meth:`BoundClip.sample_into` once per cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.clip import Clip
from runtime.compiled import CompiledClip, compile_clip
from runtime.core.channels import ChannelMap
from runtime.messages import ClipSpec


@dataclass(frozen=True)
class BoundClip:
    """A compiled clip plus the channel-vector index of each of its channels."""

    name: str
    duration: float
    channel_names: tuple[str, ...]
    channels: np.ndarray  # channel-vector index per clip channel
    compiled: CompiledClip  # sample(t, out) writes one value per clip channel
    nbytes: int
    key_count: int
    scratch: np.ndarray

    def sample_into(self, t: float, values: np.ndarray) -> None:
        """Write the clip's channel values at clip time ``t`` into the channel vector ``values``."""
        self.compiled.sample(t, self.scratch)
        values[self.channels] = self.scratch


def bind_clip(clip: Clip | ClipSpec, channels: ChannelMap) -> BoundClip:
    """Compile ``clip`` (a :class:`~models.clip.Clip`, or a protocol :class:`~runtime.messages.ClipSpec`) to
    arrays and bind it to the head's channel vector (UnknownChannel for a foreign channel)."""
    names = tuple(clip.channels)
    idx = channels.indices(names)
    compiled = compile_clip(clip, names)
    return BoundClip(clip.name, clip.duration, names, idx, compiled, int(compiled.nbytes), clip.key_count(),
                     np.empty(len(names)))
