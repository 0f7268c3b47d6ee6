"""The core's parameters: everything fixed for a run (the head's actuators, buses and channels, the daemon settings,
the strain guard and the timecode chase), in SI. Every system of the core reads them; none changes them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.headspec import HeadSpec
from runtime.config import DaemonConfig
from runtime.core.channels import ChannelMap
from runtime.core.chase import ChaseParams
from runtime.core.guard import StrainLimiter
from runtime.core.watch import WatchParams


@dataclass(frozen=True)
class CoreParams:
    """Everything fixed for a run: the head's actuators, buses, channels and the daemon settings (SI)."""

    names: tuple[str, ...]
    scale: np.ndarray  # SI per configured unit, per actuator
    period: float
    buses: tuple[tuple[str, np.ndarray], ...]  # bus name → indices of its actuators, in the bus's order
    channels: ChannelMap
    watch: WatchParams  # feedback age and following error limits
    units: tuple[str, ...]  # each actuator's config unit (messages)
    bus_of: tuple[str, ...]  # each actuator's bus
    cfg: DaemonConfig
    telemetry_every: int
    record_capacity: int
    guard: StrainLimiter | None = None  # skin-strain guard; None: no guard
    chase: ChaseParams | None = None  # timecode chase ([inputs.timecode]); None: no timecode input

    @classmethod
    def build(cls, head: HeadSpec, cfg: DaemonConfig, channels: ChannelMap,
              bus_order: Sequence[tuple[str, Sequence[str]]], guard: StrainLimiter | None = None,
              chase: ChaseParams | None = None) -> CoreParams:
        """The parameters of ``head`` run with ``cfg``; ``bus_order``: each bus's actuators in the bus's order."""
        index = {n: i for i, n in enumerate(head.actuator_names)}
        rt = cfg.runtime
        period = 1.0 / rt.rate_hz
        return cls(
            names=head.actuator_names, scale=np.array([a.unit_scale for a in head.actuators]),
            period=period,
            buses=tuple((b, np.array([index[m] for m in motors], dtype=np.intp)) for b, motors in bus_order),
            channels=channels, watch=WatchParams.build(head, cfg, tuple(b for b, _ in bus_order), period),
            units=tuple(a.unit for a in head.actuators), bus_of=tuple(a.bus for a in head.actuators), cfg=cfg,
            telemetry_every=max(1, round(rt.rate_hz / rt.telemetry_hz)),
            record_capacity=int(rt.record_max_s * rt.rate_hz) + 1, guard=guard, chase=chase,
        )
