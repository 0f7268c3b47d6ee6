"""Target solvers in the core's array form: a solver declares its channels and solves a block of the channel vector.

Solvers written against the mapping protocol of :mod:`runtime.solve` (``channels()``, ``solve(targets, current)``,
optional ``reset(positions)``) are wrapped by :class:`ArraySolver`; a solver that already has ``solve_array`` and
``reset_array`` is used as it is.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


def declared_channels(solver: Any) -> dict[str, str]:
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

    def __init__(self, solver: Any, channels: Sequence[str], actuators: Sequence[str]) -> None:
        self.solver = solver
        self.channels = tuple(channels)
        self.actuators = tuple(actuators)
        self._index = {n: i for i, n in enumerate(self.actuators)}
        self._out = np.full(len(self.actuators), np.nan)

    def solve_array(self, block: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        targets = {ch: float(v) for ch, v in zip(self.channels, block.tolist(), strict=True) if v == v}
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
        reset = getattr(self.solver, "reset", None)
        if reset is not None:
            reset(dict(zip(self.actuators, q.tolist(), strict=True)))


def as_array_solvers(solvers: Sequence[Any], blocks: Sequence[tuple[int, int, int]], names: Sequence[str],
                     actuators: Sequence[str]) -> list[Any]:
    """One array solver per target solver, each given the channel names of its block of the channel vector."""
    out = []
    for s, a, b in blocks:
        solver = solvers[s]
        if hasattr(solver, "solve_array") and hasattr(solver, "reset_array"):
            out.append(solver)
        else:
            out.append(ArraySolver(solver, names[a:b], actuators))
    return out


def channel_sets(solvers: Sequence[Any]) -> list[Mapping[str, str]]:
    return [declared_channels(s) for s in solvers]
