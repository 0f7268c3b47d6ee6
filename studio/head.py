"""The head as the studio sees it: every channel a person can pose (actuators, groups, ARKit targets) and how a
channel pose becomes an actuator pose (SI) for the skin predictor.

Channel values are in each channel's configured unit (degrees, millimetres; ``weight`` 0..1 for ``arkit.*``), as the
protocol carries them. Group channels fan out to their members with the group's gains; target channels are solved
to actuator values through the predictor's hidden-space inverse (:mod:`models.skin_targets`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.headspec import HeadSpec, load_head
from models.predictor import SkinPredictor
from models.skin_targets import PREFIX, skin_targets_for_head
from models.strain_guard import StrainGuard


@dataclass(frozen=True)
class Channel:
    """One posable channel: name, kind (``actuator``, ``group``, ``target``), unit and limits in that unit."""

    name: str
    kind: str
    unit: str
    min: float
    max: float
    neutral: float


class StudioHead:
    """A head with its skin predictor, strain guard and (when the predictor has face units) target solver."""

    def __init__(self, head: HeadSpec) -> None:
        self.spec = head
        path = head.path("predictor")
        if path is None or not Path(path).is_file():
            raise ValueError(f"{head.source}: the studio needs the head's skin predictor ([paths] predictor), "
                             f"not found: {path}")
        self.predictor = SkinPredictor(path)
        self.predictor.check_against(head, require_full_range=False)
        self.targets = skin_targets_for_head(head) if self.predictor.face_unit_offsets is not None else None
        guard = self.targets.strain_guard if self.targets is not None else StrainGuard.for_head(head, self.predictor)
        if guard is None:  # for_head returns None only without a predictor path, checked above
            raise ValueError(f"{head.source}: no strain guard for this head")
        self.guard: StrainGuard = guard
        self.names = head.actuator_names
        self._index = {n: i for i, n in enumerate(self.names)}
        self.scale = np.array([a.unit_scale for a in head.actuators])
        # The pose range: the head's limits within the predictor's trained range (no extrapolation on screen).
        self.lo = np.maximum([a.min for a in head.actuators], self.predictor.lo)
        self.hi = np.minimum([a.max for a in head.actuators], self.predictor.hi)
        self.neutral = np.clip([a.neutral for a in head.actuators], self.lo, self.hi)
        self.channels = self._channels()
        self.by_name = {c.name: c for c in self.channels}

    @classmethod
    def load(cls, config: str | Path) -> StudioHead:
        return cls(load_head(config))

    def _channels(self) -> tuple[Channel, ...]:
        out = []
        for i, a in enumerate(self.spec.actuators):
            out.append(Channel(a.name, "actuator", a.unit, self.lo[i] / self.scale[i], self.hi[i] / self.scale[i],
                               self.neutral[i] / self.scale[i]))
        for g in self.spec.groups:
            if g.name in self._index:
                continue
            first = self._index[g.actuators[0]]
            # The group value v moves member m to gain_m * v: its range is where every member stays in range.
            lo, hi = -np.inf, np.inf
            for m, gain in zip(g.actuators, g.gains, strict=True):
                k = self._index[m]
                if gain == 0:
                    continue
                a, b = sorted((self.lo[k] / gain, self.hi[k] / gain))
                lo, hi = max(lo, a), min(hi, b)
            s = self.scale[first]
            out.append(Channel(g.name, "group", self.spec.actuators[first].unit, lo / s, hi / s,
                               float(np.clip(0.0, lo / s, hi / s))))
        if self.targets is not None:
            for ch in self.targets.channels():
                out.append(Channel(ch, "target", "weight", 0.0, 1.0, 0.0))
        return tuple(out)

    # ------------------------------------------------------------------ channel → actuator pose
    def kind(self, channel: str) -> str:
        try:
            return self.by_name[channel].kind
        except KeyError:
            raise KeyError(f"unknown channel {channel!r} (not an actuator, group or target of head "
                           f"{self.spec.name!r})") from None

    def apply(self, p: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
        """Actuator pose (SI) after setting actuator and group channels (config units) on pose ``p``; target
        channels are ignored here (see :meth:`solve_targets`). The result is clipped to the pose range."""
        q = np.array(p, dtype=np.float64)
        for name, value in values.items():
            kind = self.kind(name)
            if kind == "actuator":
                k = self._index[name]
                q[k] = float(value) * self.scale[k]
            elif kind == "group":
                g = next(g for g in self.spec.groups if g.name == name)
                s = self.scale[self._index[g.actuators[0]]]
                for m, gain in zip(g.actuators, g.gains, strict=True):
                    q[self._index[m]] = gain * float(value) * s
        return np.clip(q, self.lo, self.hi)

    def solve_targets(self, weights: Mapping[str, float], p_prev: np.ndarray) -> tuple[np.ndarray, float]:
        """Actuator pose (SI) whose predicted skin best matches the ARKit weights, and the RMS residual (m)."""
        if self.targets is None:
            raise ValueError(f"head {self.spec.name!r}: the predictor has no face units, so no arkit.* channels")
        units = self.targets.units
        w = np.zeros(len(units))
        for ch, value in weights.items():
            if self.kind(ch) != "target":
                raise KeyError(f"{ch!r} is not a target channel")
            w[units[ch[len(PREFIX):]]] = min(max(float(value), 0.0), 1.0)
        res = self.targets.inverse.solve(w, p_prev=np.clip(p_prev, self.lo, self.hi), max_iterations=30, tol=1e-10)
        return np.clip(res.p, self.lo, self.hi), float(res.residual_rms)

    def channel_values(self, p: np.ndarray) -> dict[str, float]:
        """Actuator channels of pose ``p`` (SI) in config units."""
        return {n: float(p[i] / self.scale[i]) for i, n in enumerate(self.names)}

    def pose_from_channels(self, values: Mapping[str, float], p_prev: np.ndarray | None = None) -> np.ndarray:
        """Actuator pose (SI) for a channel sample (as a clip gives it): targets are solved first, then actuator
        and group channels set on top (so a clip may mix both)."""
        p = self.neutral.copy() if p_prev is None else np.array(p_prev, dtype=np.float64)
        targets = {k: v for k, v in values.items() if k in self.by_name and self.by_name[k].kind == "target"}
        if targets:
            p, _ = self.solve_targets(targets, p)
        direct = {k: v for k, v in values.items() if k in self.by_name and self.by_name[k].kind != "target"}
        return self.apply(p, direct)
