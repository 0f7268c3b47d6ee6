"""The layout design's discrete step: attachment node sets grown or shrunk by whole rings between continuous design
rounds.

A round screens every allowed change (each attachment set, +1 and −1 ring, :mod:`offline.design.attachment_rings`)
by the design objective F at the current design and actuation: the FEM poses of every target solved again with the
changed set, warm-started from the current equilibria (the Dirichlet set changes with each candidate, so no
factorization carries over from one candidate to the next). The best improving change of each set are then tried
together; the round keeps the combination when it beats the best single change, else the best single change. A
change is improving when it lowers F by at least ``RingSettings.tol`` relative. The job then runs the continuous
design again (layout and actuation together) from there, and screens again, until no change improves enough, every
set is at its ring limit, or ``max_rounds``.

The new nodes move rigidly with the link body that carries the set, as the others: the design boundary reads the
sets from the skin mesh, which the step replaces (nodes and tets unchanged). The strain measure is the original
head's (its attachment rims are not recomputed), the guard's footprint the written head carries.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .actuation import evaluate
from .attachment_rings import AttachmentRings, Candidate
from .mechanism_design import LayoutProblem, LayoutState

Progress = Callable[[str], None]


@dataclass(frozen=True)
class RingSettings:
    """The ring step's stopping rule: a change must lower F by ``tol`` (relative); at most ``max_rounds`` rounds."""

    tol: float = 1e-3
    max_rounds: int = 3


class RingStep:
    """The attachment sets of a layout problem's skin, their ring limits and current counts."""

    def __init__(self, lp: LayoutProblem, limits: Mapping[str, int] | None = None) -> None:
        skin = lp.face.skin
        self.lp = lp
        self.base_mesh = skin.mesh
        self.links = {s: link for link, s in skin.moving.items()}  # node set → link
        self.rings = AttachmentRings(skin.mesh, list(self.links), fixed=[skin.spec.skull_set],
                                     surface_nodes=lp.face.inner)
        self.limits = dict(limits if limits is not None else lp.space.envelope.ring_limits(list(self.links)))
        self.counts: dict[str, int] = {n: 0 for n in self.rings.names}

    @property
    def active(self) -> bool:
        """Whether any set may change at all."""
        return any(v > 0 for v in self.limits.values())

    def vector(self) -> np.ndarray:
        return np.array([self.counts[n] for n in self.rings.names], dtype=np.int64)

    def set_counts(self, counts: Mapping[str, int] | np.ndarray) -> None:
        """Put every set at ``counts`` (a mapping, or a vector in name order) in the skin the problem solves."""
        if isinstance(counts, np.ndarray):
            counts = dict(zip(self.rings.names, (int(v) for v in counts), strict=True))
        self.counts = {n: int(counts.get(n, 0)) for n in self.rings.names}
        self.lp.face.skin.mesh = self.rings.mesh_at(self.counts)

    def node_sets(self) -> dict[str, np.ndarray]:
        """The sets at the current counts."""
        return self.rings.sets_at(self.counts)

    def candidates(self) -> list[Candidate]:
        return self.rings.candidates(self.counts, self.limits)

    def summary(self) -> list[dict[str, Any]]:
        """Per set: its link, rings changed, nodes before and after."""
        now = self.node_sets()
        return [{"node_set": n, "link": self.links[n], "rings": self.counts[n], "limit": self.limits[n],
                 "nodes_before": len(self.rings.original[n]), "nodes_after": len(now[n])} for n in self.rings.names]


def objective_at(lp: LayoutProblem, state: LayoutState) -> tuple[float, list[np.ndarray]] | None:
    """F at the state's design and actuation on the skin as it is now (poses warm-started from the state's
    equilibria); None when a pose does not converge."""
    total, X = 0.0, []
    for k, target in enumerate(lp.targets):
        ev = evaluate(lp.problem, state.Z[k], target, state.X[k], strain_weight=float(state.weights[k]))
        if ev is None:
            return None
        total += ev.value
        X.append(ev.x)
    return total + lp.regularization(state.theta)[0], X


def screen(step: RingStep, state: LayoutState, settings: RingSettings, progress: Progress = print
           ) -> dict[str, Any]:
    """One round: every allowed change screened by F at the current design and actuation, the best improving
    one(s) applied to ``step`` (and ``state.X`` updated to the new equilibria). Returns the round's record."""
    lp = step.lp
    lp.boundary.set_design(state.theta)
    start = dict(step.counts)
    base = objective_at(lp, state)
    if base is None:
        raise RuntimeError("the current design does not give converged poses for every target")
    F0 = base[0]
    allowed = [c for c in step.candidates() if c.allowed]
    progress(f"[rings] screening {len(allowed)} change(s) at objective {F0:.5g}")
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, c in enumerate(allowed):
        step.set_counts({**start, c.name: c.rings + c.step})
        res = objective_at(lp, state)
        F = None if res is None else res[0]
        rows.append({"node_set": c.name, "step": c.step, "nodes_before": c.nodes_before, "nodes_after": c.nodes_after,
                     "objective": F, "relative_change": None if F is None else (F - F0) / abs(F0)})
        left = (len(allowed) - i - 1) * (time.perf_counter() - t0) / (i + 1)
        progress(f"[rings] {i + 1}/{len(allowed)} {c.name} {c.step:+d} ring ({c.nodes_before} -> {c.nodes_after} "
                 f"nodes): objective {'not converged' if F is None else f'{F:.5g}'}  ETA {left / 60:.1f} min")
    step.set_counts(start)
    good = [r for r in rows if r["objective"] is not None and r["relative_change"] <= -settings.tol]
    record: dict[str, Any] = {"objective_before": F0, "screened": rows, "applied": [], "objective_after": F0}
    if not good:
        progress(f"[rings] no change lowers the objective by {settings.tol:.0e} (relative): the ring step stops")
        return record
    best: dict[str, dict[str, Any]] = {}
    for r in sorted(good, key=lambda r: r["objective"]):
        best.setdefault(r["node_set"], r)
    single = min(good, key=lambda r: r["objective"])
    choice, F_choice, X_choice = [single], single["objective"], None
    if len(best) > 1:
        step.set_counts({**start, **{n: start[n] + r["step"] for n, r in best.items()}})
        res = objective_at(lp, state)
        progress(f"[rings] the best change of {len(best)} sets together: objective "
                 f"{'not converged' if res is None else f'{res[0]:.5g}'} (best single {F_choice:.5g})")
        if res is not None and res[0] < F_choice:
            choice, F_choice, X_choice = list(best.values()), res[0], res[1]
    step.set_counts({**start, **{r["node_set"]: start[r["node_set"]] + r["step"] for r in choice}})
    if X_choice is None:
        res = objective_at(lp, state)
        if res is None:
            raise RuntimeError("the chosen ring change no longer converges")
        F_choice, X_choice = res
    state.X = list(X_choice)
    record.update(applied=[{"node_set": r["node_set"], "step": r["step"], "nodes_before": r["nodes_before"],
                            "nodes_after": r["nodes_after"]} for r in choice], objective_after=F_choice)
    progress("[rings] applied " + ", ".join(f"{r['node_set']} {r['step']:+d}" for r in choice)
             + f": objective {F0:.5g} -> {F_choice:.5g}")
    return record


def dry_run_lines(step: RingStep) -> list[str]:
    """The candidate changes of the first round, for ``--dry-run``."""
    lines = [f"attachment rings: limits {', '.join(f'{n} {v}' for n, v in step.limits.items())}"]
    for c in step.candidates():
        what = f"{c.nodes_before} -> {c.nodes_after} nodes" if c.allowed else f"not allowed: {c.why}"
        lines.append(f"  {c.name} ({step.links[c.name]}) {c.step:+d} ring: {what}")
    return lines
