"""The target-solver protocol: target-space channels (``arkit.jawOpen``, link poses) → actuator targets (SI).

A solver declares its channels; the control core's solve stage (``runtime.core.core.solve_channels``) hands it the
values of those channels each cycle, and takes actuator targets plus optional telemetry fields (residual,
predicted poses). Explicit actuator channels win over group channels, which win over solved targets.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable


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
    extra: dict[str, Any] = field(default_factory=dict)
