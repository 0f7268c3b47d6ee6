"""The solve stage between timeline and safety: channel values → actuator targets (SI).

Actuator channels (``jaw``) pass through, converted from their configured unit; group channels (``blink``) expand
to their members with the group's gains; target channels (``arkit.jawOpen``, link poses) go to pluggable
:class:`TargetSolver`s, which return actuator targets plus optional telemetry fields (residual, predicted poses).
Explicit actuator channels win over group channels, which win over solved targets.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from models.headspec import HeadSpec


class UnknownChannel(KeyError):
    """A channel names no actuator, group or target of the head."""


@runtime_checkable
class TargetSolver(Protocol):
    """Solves target-space channels (e.g. ARKit weights through a skin predictor) to actuator positions."""

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


class Solver:
    """Maps channel values of one head to actuator targets."""

    def __init__(self, head: HeadSpec, target_solvers: Iterable[TargetSolver] = ()) -> None:
        self.head = head
        self._scale = {a.name: a.unit_scale for a in head.actuators}
        self._groups = {
            g.name: tuple((m, gain, self._scale[m]) for m, gain in zip(g.actuators, g.gains, strict=True))
            for g in head.groups
            if g.name not in self._scale
        }
        # A group channel carries the unit of its first member.
        self._group_scale = {g: members[0][2] for g, members in self._groups.items()}
        self.target_solvers: list[TargetSolver] = list(target_solvers)

    def add_target_solver(self, solver: TargetSolver) -> None:
        self.target_solvers.append(solver)

    def channel_kind(self, channel: str) -> str:
        """"actuator", "group" or "target"; raises :class:`UnknownChannel`."""
        if channel in self._scale:
            return "actuator"
        if channel in self._groups:
            return "group"
        if any(s.handles(channel) for s in self.target_solvers):
            return "target"
        raise UnknownChannel(channel)

    def check_channels(self, channels: Iterable[str]) -> None:
        """Raise :class:`UnknownChannel` naming the first channel the head does not know."""
        for ch in channels:
            self.channel_kind(ch)

    def channels(self) -> dict[str, str]:
        """Known actuator and group channels with their units."""
        out = {a.name: a.unit for a in self.head.actuators}
        for g, members in self._groups.items():
            out[g] = self.head.actuator(members[0][0]).unit
        return out

    def solve(self, values: Mapping[str, float], current: Mapping[str, float]) -> SolveResult:
        """Actuator targets (SI) for channel values in configured units; actuators not addressed are absent."""
        out: dict[str, float] = {}
        extra: dict[str, Any] = {}
        if self.target_solvers:
            for solver in self.target_solvers:
                mine = {ch: v for ch, v in values.items() if ch not in self._scale and ch not in self._groups
                        and solver.handles(ch)}
                if mine:
                    res = solver.solve(mine, current)
                    out.update(res.actuators)
                    extra.update(res.extra)
        for ch, v in values.items():
            members = self._groups.get(ch)
            if members is not None:
                scale = self._group_scale[ch]
                for m, gain, _ in members:
                    out[m] = gain * v * scale
        for ch, v in values.items():
            scale = self._scale.get(ch)
            if scale is not None:
                out[ch] = v * scale
        return SolveResult(out, extra)
