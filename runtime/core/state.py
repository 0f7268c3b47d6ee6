"""The core's state: one part per system, kept apart from the code that steps it (after Drake's Context).

Each stage changes its own part; the composition (:mod:`runtime.core.core`) carries what one stage's outcome means
for another (a fault stops the sources and resets the solvers). :class:`CoreState` composes the parts; the loop
runner, the daemon and tests read the lifecycle, mode, source, timeline, shaper and safety filter under those names.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.headspec import HeadSpec
from runtime.core.buses import BusesState
from runtime.core.chase import Chase
from runtime.core.guard import GuardState
from runtime.core.lifecycle import Lifecycle, LifecycleState
from runtime.core.params import CoreParams
from runtime.core.recorder import RecorderState
from runtime.core.shape import make_shaper
from runtime.core.solve import SolveState
from runtime.core.solvers import ArrayTargetSolver
from runtime.core.sources import Mode, SourcesState
from runtime.core.watch import WatchState
from runtime.safety import SafetyFilter
from runtime.shaper import Shaper
from runtime.timeline import Timeline


@dataclass
class CoreState:
    """All mutable state of the control core (the daemon's only state that changes at loop rate), by system."""

    life: LifecycleState  # lifecycle, bus transition under way, fault, e-stop
    feedback: BusesState  # the buses' latest feedback
    sources: SourcesState  # what drives the head: clips, stream, live values, pose
    solve: SolveState  # target solvers (warm starts) and their extra telemetry
    guard: GuardState  # the skin-strain guard's last accepted target and verdict
    recorder: RecorderState
    safety: SafetyFilter  # limits, groups, neutral (stateless use: constrain against the shaper's command)
    shaper: Shaper  # commanded position, velocity and acceleration (jerk-limited, ruckig)
    watch: WatchState  # feedback age and following error: what was posted, since when an error is exceeded
    chase: Chase | None = None  # timecode chase, when a timecode input is configured
    out_of_range: np.ndarray | None = None  # actuators enabled outside their limits and not yet back (None: none)
    cycle: int = 0
    last_t: float | None = None  # the time of the last full cycle (the shaper advances by what passed since)

    @classmethod
    def initial(cls, head: HeadSpec, params: CoreParams, solvers: Sequence[ArrayTargetSolver] = ()) -> CoreState:
        """The state at start-up: inactive, holding at neutral, nothing loaded; ``solvers`` one per target block."""
        return cls(
            life=LifecycleState(), feedback=BusesState.initial(params), sources=SourcesState.initial(params),
            solve=SolveState(list(solvers)), guard=GuardState(), recorder=RecorderState(),
            safety=SafetyFilter(head), shaper=make_shaper(head, params.period),
            watch=WatchState.initial(len(params.names)),
            chase=None if params.chase is None else Chase(params.chase),
        )

    @property
    def lifecycle(self) -> Lifecycle:
        """The head's lifecycle."""
        return self.life.lifecycle

    @property
    def mode(self) -> Mode:
        """Which source drives the head."""
        return self.sources.mode

    @property
    def source(self) -> str | None:
        """The input driving the head ("api", "osc", "sacn", "timecode"; None: nothing)."""
        return self.sources.source

    @property
    def timeline(self) -> Timeline:
        """The loaded clips and the one playing."""
        return self.sources.timeline
