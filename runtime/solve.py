"""The target-solver protocol: target-space channels (``arkit.jawOpen``, attachment-link poses) → actuator targets (SI).

A solver declares its channels; the daemon takes solvers of this type (``Daemon(target_solvers=...)``,
:func:`runtime.skin.default_target_solvers`), the core adapts them to its array form
(:mod:`runtime.core.solvers`), and its solve stage (``runtime.core.core.solve_channels``) hands each the values of
its channels each cycle, and takes actuator targets plus optional telemetry fields (residual,
predicted poses). Explicit actuator channels win over group channels, which win over solved targets.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

#: Telemetry fields a solve adds (residual, iterations, guard verdict...): plain numbers, strings, number lists.
SolveExtra = dict[str, float | int | str | list[float]]


@runtime_checkable
class TargetSolver(Protocol):
    """Solves target-space channels (e.g. ARKit weights through a skin predictor) to actuator positions."""

    def channels(self) -> Mapping[str, str]:
        """The channels this solver owns, with their units (listed by ``hello``)."""
        ...

    def handles(self, channel: str) -> bool:
        """Whether this solver owns ``channel``."""
        ...

    def solve(self, targets: Mapping[str, float], current: Mapping[str, float]) -> SolveResult:
        """Actuator targets (SI) for the given target-channel values; ``current`` is the last command (SI)."""
        ...


@dataclass
class SolveResult:
    """Actuator targets (SI, by actuator name) and optional extra telemetry fields."""

    actuators: dict[str, float]
    extra: SolveExtra = field(default_factory=dict)
