"""The channel space of one head: every channel a source may address, as indices into one value vector.

Actuator channels (``jaw``) pass through in their configured unit; group channels (``blink``) fan out to their members
with the group's gains; target channels (``arkit.jawOpen``) are solved by the head's target solvers. A
:class:`ChannelMap` is built once, from the head and the channels the target solvers declare, and is shared (pickled)
by the API server, which compiles clips and frames onto these indices, and the control core, which evaluates them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from models.headspec import HeadSpec


class UnknownChannel(KeyError):
    """A channel names no actuator, group or target of the head."""


@dataclass(frozen=True)
class ChannelMap:
    """Channel names → indices, with the arrays the solve stage needs (all SI conversions precomputed)."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    n_actuators: int
    # actuator channels: channel k < n_actuators is actuator k; value * act_scale[k] is SI
    act_scale: np.ndarray
    # group channels: one row per (group channel, member): channel index, actuator index, gain * SI scale
    group_channel: np.ndarray
    group_member: np.ndarray
    group_factor: np.ndarray
    # target channels: [target_start, n) grouped per solver: (solver index, first, stop)
    target_start: int
    target_blocks: tuple[tuple[int, int, int], ...]

    @classmethod
    def build(cls, head: HeadSpec, target_channels: Sequence[Mapping[str, str]] = ()) -> ChannelMap:
        """Actuators first (head order), then groups that are not actuator names, then each solver's targets."""
        acts = head.actuators
        index = {a.name: i for i, a in enumerate(acts)}
        names = [a.name for a in acts]
        units = [a.unit for a in acts]
        gc: list[int] = []
        gm: list[int] = []
        gf: list[float] = []
        for g in head.groups:
            if g.name in index:
                continue
            k = len(names)
            names.append(g.name)
            first = head.actuator(g.actuators[0])
            units.append(first.unit)
            for m, gain in zip(g.actuators, g.gains, strict=True):
                gc.append(k)
                gm.append(index[m])
                gf.append(float(gain) * first.unit_scale)
        start = len(names)
        blocks = []
        for s, chans in enumerate(target_channels):
            first_k = len(names)
            for ch, unit in chans.items():
                if ch in names:
                    continue
                names.append(ch)
                units.append(unit)
            blocks.append((s, first_k, len(names)))
        return cls(tuple(names), tuple(units), len(acts), np.array([a.unit_scale for a in acts]),
                   np.array(gc, dtype=np.intp), np.array(gm, dtype=np.intp), np.array(gf), start, tuple(blocks))

    @property
    def n(self) -> int:
        return len(self.names)

    def index_of(self, channel: str) -> int:
        try:
            return self._index[channel]
        except KeyError:
            raise UnknownChannel(channel) from None

    def indices(self, channels: Iterable[str]) -> np.ndarray:
        """Indices of ``channels``; :class:`UnknownChannel` names the first unknown one."""
        return np.array([self.index_of(c) for c in channels], dtype=np.intp)

    def kind(self, channel: str) -> str:
        k = self.index_of(channel)
        return "actuator" if k < self.n_actuators else "group" if k < self.target_start else "target"

    def described(self) -> dict[str, str]:
        """Channel → unit, as ``hello`` lists them."""
        return dict(zip(self.names, self.units, strict=True))

    @property
    def _index(self) -> dict[str, int]:
        cached = self.__dict__.get("_index_cache")
        if cached is None:
            cached = {n: i for i, n in enumerate(self.names)}
            object.__setattr__(self, "_index_cache", cached)
        return cached

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state.pop("_index_cache", None)
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
