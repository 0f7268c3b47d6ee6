"""Target solvers in the core's array form: a solver declares its channels and solves a block of the channel vector.

:class:`ArrayTargetSolver` is what the core calls. Solvers written against the mapping protocol of
:mod:`runtime.solve` (``channels()``, ``solve(targets, current)``, optional ``reset(positions)``) are wrapped by
:class:`ArraySolver`; a solver that already has ``solve_array`` and ``reset_array`` is used as it is.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np

from runtime.solve import TargetSolver


class ArrayTargetSolver(Protocol):
    """A target solver as the core calls it: the channels it declares, a solve on arrays, a reset of warm starts."""

    def channels(self) -> Mapping[str, str]:
        """The channels it solves (name → unit), listed by ``hello``; its block of the channel vector, in order."""
        ...

    def solve_array(self, block: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, Mapping[str, object]]:
        """Actuator targets (SI, NaN: not addressed) for its block of channel values (NaN: not set), from the
        present command ``q``; plus extra telemetry fields (residual, predicted poses), which the core copies when it
        reports them: both may be the solver's own, updated by its next solve."""
        ...

    def reset_array(self, q: np.ndarray) -> None:
        """Forget warm starts: the next solve starts from the command ``q`` (enable, fault, e-stop, reset)."""
        ...


def declared_channels(solver: object) -> dict[str, str]:
    """The channels a target solver declares (``channels()``: name → unit); a solver must declare them."""
    chans = getattr(solver, "channels", None)
    if chans is None:
        raise TypeError(f"target solver {type(solver).__name__} declares no channels (needs channels() -> "
                        "{name: unit})")
    out = dict(chans())
    if not out or not all(isinstance(k, str) and isinstance(v, str) for k, v in out.items()):
        raise TypeError(f"target solver {type(solver).__name__}: channels() must map channel names to units")
    return out


class ArraySolver:
    """Adapts a mapping-protocol target solver to ``solve_array(block, q) -> (targets SI | NaN, extra)``."""

    def __init__(self, solver: TargetSolver, channels: Sequence[str], actuators: Sequence[str]) -> None:
        self.solver = solver
        self.names = tuple(channels)
        self.actuators = tuple(actuators)
        self._index = {n: i for i, n in enumerate(self.actuators)}
        self._out = np.full(len(self.actuators), np.nan)

    def channels(self) -> Mapping[str, str]:
        """The wrapped solver's channels."""
        return self.solver.channels()

    def solve_array(self, block: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, Mapping[str, object]]:
        """The wrapped solver on the set values of ``block``, its result as an actuator vector."""
        targets = {ch: float(v) for ch, v in zip(self.names, block.tolist(), strict=True) if v == v}
        current = dict(zip(self.actuators, q.tolist(), strict=True))
        res = self.solver.solve(targets, current)
        out = self._out
        out.fill(np.nan)
        for name, value in res.actuators.items():
            i = self._index.get(name)
            if i is not None:
                out[i] = value
        return out, res.extra

    def reset_array(self, q: np.ndarray) -> None:
        """The wrapped solver's ``reset`` (when it has one) at the command ``q``."""
        reset = getattr(self.solver, "reset", None)
        if reset is not None:
            reset(dict(zip(self.actuators, q.tolist(), strict=True)))


def as_array_solvers(solvers: Sequence[TargetSolver | ArrayTargetSolver], blocks: Sequence[tuple[int, int, int]],
                     names: Sequence[str], actuators: Sequence[str]) -> list[ArrayTargetSolver]:
    """One array solver per target solver, each given the channel names of its block of the channel vector.

    A solver with the array form is used as it is when its block holds exactly the channels it declares, in order
    (its block is then indexed as it expects); when a channel it declares went to an earlier solver or a group, a
    solver that also has the mapping API is adapted by name instead."""
    out: list[ArrayTargetSolver] = []
    for s, a, b in blocks:
        solver = solvers[s]
        native = hasattr(solver, "solve_array") and hasattr(solver, "reset_array")
        if native and (tuple(names[a:b]) == tuple(declared_channels(solver)) or not hasattr(solver, "solve")):
            out.append(solver)  # has the array form already
        else:
            out.append(ArraySolver(solver, names[a:b], actuators))
    return out


def channel_sets(solvers: Sequence[object]) -> list[Mapping[str, str]]:
    """The channels each target solver declares, in order (the channel map's target blocks)."""
    return [declared_channels(s) for s in solvers]
