"""Target-space channels solved through the learned skin: ``arkit.<faceUnit>`` weights → actuator values.

The weights define a target surface (base + Σ wᵢ Δᵢ, the face units stored in the predictor file); the hidden-space
inverse (``models.ksnn_solve``) finds the actuator values whose predicted skin matches it, warm-started from the
previous frame with temporal smoothness, within the head's limits and the predictor's trained range. The skin-strain
guard (:class:`models.strain_guard.StrainGuard`, its reduced in-cycle check) then checks the solution: a pose whose
strain measure leaves the material's validated range (default −20 % .. +50 %, ``docs/skin_guard.md``) is pulled back
toward the last accepted pose until it passes, or the last accepted pose is held. Telemetry carries the solve
residual, iterations, time and guard outcome.

The control core calls :meth:`SkinTargetSolver.solve_array` every cycle: its block of the channel vector in, the
actuator vector out, through one compiled call (:class:`models.ksnn_solve.FrameSolve`) with no per-cycle dictionaries
or string handling; the telemetry fields are a view (:class:`SkinTelemetry`) formatted only when the status snapshot
reads them. :meth:`SkinTargetSolver.solve` is the same solve by channel name. Imports only numpy, scipy and
onnxruntime (via models).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from models.headspec import HeadSpec
from models.predictor import DEFAULT_STRAIN_RANGE, SkinPredictor
from models.skin_targets import PREFIX, SkinTargets, skin_targets, skin_targets_for_head
from models.strain_guard import StrainGuard
from runtime.solve import SolveResult, TargetSolver

#: Bisections of the guard's search when a frame's solution leaves the strain range (1/32 of the way back).
GUARD_STEPS = 5


class SkinTelemetry(Mapping[str, float | int | str | list[float]]):
    """The telemetry fields of the last skin solve (``skin_residual_mm``, ``skin_iterations``, ``skin_solve_us``,
    ``skin_strain``, ``skin_guard``): the raw figures, formatted only when a field is read.

    One per solver, updated in place by every solve, so a control cycle builds no dictionary and rounds nothing; the
    core's status snapshot copies it (``dict(...)``) at its own period. Read it before the next solve.
    """

    KEYS = ("skin_residual_mm", "skin_iterations", "skin_solve_us", "skin_strain", "skin_guard")

    def __init__(self) -> None:
        self.residual_rms = 0.0  # m
        self.iterations = 0
        self.solve_us = 0.0
        self.strain: tuple[float, float] = (0.0, 0.0)
        self.guard = "ok"

    def __getitem__(self, key: str) -> float | int | str | list[float]:
        if key == "skin_residual_mm":
            return self.residual_rms * 1e3
        if key == "skin_iterations":
            return self.iterations
        if key == "skin_solve_us":
            return self.solve_us
        if key == "skin_strain":
            return [round(self.strain[0], 4), round(self.strain[1], 4)]
        if key == "skin_guard":
            return self.guard
        raise KeyError(key)

    def __iter__(self) -> Iterator[str]:
        return iter(self.KEYS)

    def __len__(self) -> int:
        return len(self.KEYS)


class SkinTargetSolver:
    """:class:`runtime.solve.TargetSolver` for ``arkit.*`` channels of a head with a skin predictor, and the core's
    array form of it (:class:`runtime.core.solvers.ArrayTargetSolver`: ``solve_array``, ``reset_array``).

    ``max_iterations``, ``tol`` and ``xtol`` are bound into the frame solve at construction.
    """

    def __init__(self, targets: SkinTargets, xtol: float = 1e-3) -> None:
        self.head = targets.head
        self.predictor = targets.predictor
        self.names = targets.predictor.actuator_names
        self.units = targets.units
        # Solutions stay where the head allows and the predictor was trained (no extrapolation).
        self.lo, self.hi = targets.lo, targets.hi
        self.inverse = targets.inverse
        self.max_iterations = targets.max_iterations  # per frame: the warm start carries the solve across frames
        self.tol = targets.tol
        # A frame whose Gauss-Newton step moves no actuator by more than this fraction of its range is done: on the
        # sample performance at 500 Hz most frames then take one iteration, within 0.02° of running all of them.
        self.xtol = xtol
        self.neutral = np.array(self.head.neutral_pose, dtype=np.float64)
        self.strain_guard = targets.strain_guard
        self.strain_range = targets.strain_guard.strain_range
        self._accepted = self.neutral.copy()
        self._index = {PREFIX + n: i for n, i in self.units.items()}  # channel → face unit (its place in the block)
        # the bound in-cycle solve
        self.frame = self.inverse.frame_solve(self.max_iterations, self.tol, xtol, self.strain_guard,
                                              guard_steps=GUARD_STEPS)
        self._out = np.empty(len(self.names))  # solve_array's result
        self.telemetry = SkinTelemetry()
        # compile (or load) the fused solve-and-measure kernel now, never in a control cycle
        self.frame(self.frame.values, self.neutral)
        self.frame.reuse.forget()

    @classmethod
    def build(cls, head: HeadSpec, predictor: SkinPredictor | str | Path,
              strain_range: tuple[float, float] = DEFAULT_STRAIN_RANGE, smoothness: float = (0.1e-3) ** 2,
              max_iterations: int = 3, tol: float = 1e-6, strain_guard: StrainGuard | None = None,
              xtol: float = 1e-3) -> SkinTargetSolver:
        """The solver of ``head`` on ``predictor`` with explicit settings (:func:`models.skin_targets.skin_targets`)."""
        return cls(skin_targets(head, predictor, strain_range, smoothness, max_iterations, tol, strain_guard), xtol)

    @classmethod
    def from_head(cls, head: HeadSpec) -> SkinTargetSolver | None:
        """The solver for the head's ``paths.predictor`` with its ``[skin]`` settings, or None when it names none
        (:func:`models.skin_targets.skin_targets_for_head` says what each setting does and which files are
        required)."""
        # the loop runs the solve and the guard on the predictor's weights, never a full pass: no onnxruntime session
        targets = skin_targets_for_head(head, session=False)
        return None if targets is None else cls(targets)

    # ------------------------------------------------------------------ TargetSolver protocol
    def handles(self, channel: str) -> bool:
        return channel.startswith(PREFIX) and channel[len(PREFIX):] in self.units

    def channels(self) -> dict[str, str]:
        """The target channels this solver owns (unit: blendshape weight, 0..1)."""
        return {PREFIX + n: "weight" for n in self.units}

    def solve(self, targets: Mapping[str, float], current: Mapping[str, float]) -> SolveResult:
        """Actuator values (SI) for the addressed face-unit weights (unaddressed units count as 0)."""
        t0 = time.perf_counter()
        values = self.frame.values
        values.fill(np.nan)
        index = self._index
        for ch, value in targets.items():
            i = index.get(ch)
            if i is not None:
                values[i] = value
        p = self._step(values, t0)
        return SolveResult(dict(zip(self.names, p.tolist(), strict=True)), dict(self.telemetry))

    # ------------------------------------------------------------------ the core's array form
    def solve_array(self, block: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, SkinTelemetry]:
        """Actuator values (SI, head order) for the block of ``arkit.*`` channel values in :meth:`channels` order
        (NaN: not set, counts as 0), and the telemetry view; the array is reused by the next call. ``q`` is not
        needed: the solve starts from its own last accepted pose."""
        p = self._step(block, time.perf_counter())
        out = self._out
        out[:] = p
        return out, self.telemetry

    def reset_array(self, q: np.ndarray) -> None:
        """:meth:`reset` at the command ``q`` (head order; a non-finite value: that actuator from neutral)."""
        acc = self.neutral.copy()
        ok = np.isfinite(q)
        acc[ok] = np.minimum(np.maximum(q[ok], self.lo[ok]), self.hi[ok])
        self._accepted = acc
        self.frame.reuse.forget()  # the warm start jumped: its Gauss-Newton matrix is formed afresh

    def _step(self, values: np.ndarray, t0: float) -> np.ndarray:
        """One frame: the compiled solve of ``values`` from the last accepted pose with the guard's verdict on it
        (and its limit when it fails) in the same call, the telemetry figures; returns the accepted pose."""
        frame = self.frame
        p = frame(values, self._accepted)
        self._accepted = p
        tel = self.telemetry
        tel.residual_rms = frame.residual_rms
        tel.iterations = frame.iterations
        tel.strain = frame.strain
        tel.guard = frame.verdict
        tel.solve_us = (time.perf_counter() - t0) * 1e6
        return p

    @property
    def accepted(self) -> np.ndarray:
        """The last accepted pose (a copy): the next solve's warm start."""
        return self._accepted.copy()

    # ------------------------------------------------------------------ strain guard
    def strain(self, p: np.ndarray) -> tuple[float, float]:
        """The guard's reduced strain measure (min, max) at pose p."""
        return self.strain_guard.measure(p)

    def guard(self, p: np.ndarray, steps: int = GUARD_STEPS) -> tuple[np.ndarray, str, tuple[float, float]]:
        """Accept p if the guard passes it; else the furthest passing point toward p from the last accepted pose
        (bisection), else hold the last accepted pose. Returns (pose, "ok"|"limited"|"held", strain)."""
        pose, outcome = self.strain_guard.limit(self._accepted, p, steps)
        return pose, outcome, self.strain_guard.measure(pose)

    def reset(self, positions: Mapping[str, float] | None = None) -> None:
        """Forget the warm start (on enable, fault, e-stop and reset): continue from ``positions`` or neutral."""
        self._accepted = self.neutral.copy()
        self.frame.reuse.forget()
        if positions:
            for i, n in enumerate(self.names):
                if n in positions and np.isfinite(positions[n]):
                    self._accepted[i] = min(max(float(positions[n]), self.lo[i]), self.hi[i])


def default_target_solvers(head: HeadSpec) -> list[TargetSolver]:
    """Target solvers a head's config asks for: the skin solver when ``paths.predictor`` exists."""
    skin = SkinTargetSolver.from_head(head)
    return [skin] if skin is not None else []
