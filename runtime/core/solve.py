"""The solve stage: a channel vector (config units, NaN = not addressed) → actuator targets (SI, NaN = hold).

Explicit actuator channels win over group channels, which win over solved targets. :class:`SolveState` keeps the
target solvers (their warm starts are state: reset on enable, fault, e-stop and reset) and the extra telemetry
fields the last solve gave.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from models.kernel_support import kernels_available
from models.kernels_aot import kernel
from runtime.core.channels import ChannelMap
from runtime.core.solvers import ArrayTargetSolver


@dataclass
class SolveState:
    """The target solvers, one per target block of the channel map, and the last solve's extra fields."""

    solvers: list[ArrayTargetSolver] = field(default_factory=list)
    extra: Mapping[str, object] = field(default_factory=dict)


def to_targets(sv: SolveState, cm: ChannelMap, q: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Actuator targets for the channel vector ``values``; ``q``: the present command (the solvers' start)."""
    x = np.full(cm.n_actuators, np.nan)
    for s, a, b in cm.target_blocks:
        seg = values[a:b]
        if not np.isfinite(seg).any():
            continue
        p, extra = sv.solvers[s].solve_array(seg, q)
        np.copyto(x, p, where=np.isfinite(p))
        if extra:
            sv.extra = extra
    if kernels_available():  # the group and actuator channels in one compiled call
        kernel("channel_targets")(values, x, cm.group_channel, cm.group_member, cm.group_factor, cm.act_scale)
        return x
    return _channels_numpy(cm, values, x)


def _channels_numpy(cm: ChannelMap, values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """:func:`models._cycle_kernels.channel_targets` in numpy (without numba; the reference the tests compare)."""
    if cm.group_channel.size:
        gv = values[cm.group_channel]
        ok = np.isfinite(gv)
        if ok.any():
            x[cm.group_member[ok]] = gv[ok] * cm.group_factor[ok]
    av = values[:cm.n_actuators]
    ok = np.isfinite(av)
    x[ok] = av[ok] * cm.act_scale[ok]
    return x


def reset(sv: SolveState, q: np.ndarray) -> None:
    """Every solver starts afresh from the command ``q``."""
    for s in sv.solvers:
        s.reset_array(q)
