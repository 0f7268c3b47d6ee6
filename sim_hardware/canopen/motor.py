"""Motor and position-loop model of an emulated drive, stepped in simulated time (counts domain).

A stiff velocity loop with a proportional position loop on top: the commanded velocity is the
feed-forward of the demand plus ``kp`` times the following error, clamped to the velocity limit;
the acceleration needed to reach it is clamped by the current limit through the rotor inertia and
torque constant. With the power stage off the rotor coasts down. A jammed rotor does not move and
draws the current limit whenever the loop is closed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class MotorParams:
    """Physical constants of the emulated motor (SI at the motor shaft)."""

    counts_per_rev: int = 4096
    inertia: float = 2e-5  # kg·m², rotor plus reflected load
    torque_constant: float = 0.1  # N·m/A
    viscous_friction: float = 1e-5  # N·m/(rad/s)
    kp: float = 300.0  # 1/s, position loop gain
    coast_time_constant: float = 0.05  # s, velocity decay with the power stage off

    @property
    def rad_per_count(self) -> float:
        return 2.0 * math.pi / self.counts_per_rev


@dataclass(slots=True)
class MotorState:
    """Continuous state of the rotor in counts."""

    position: float = 0.0  # counts
    velocity: float = 0.0  # counts/s
    current: float = 0.0  # A, signed
    jammed: bool = False


def step_closed_loop(
    params: MotorParams,
    state: MotorState,
    demand: float,
    velocity_ff: float,
    dt: float,
    max_velocity: float,
    max_current: float,
) -> None:
    """Advance one step with the position loop closed around ``demand`` (counts)."""
    r = params.rad_per_count
    if state.jammed:
        state.velocity = 0.0
        error = demand - state.position
        state.current = math.copysign(max_current, error) if abs(error) > 0.5 else 0.0
        return
    v_cmd = velocity_ff + params.kp * (demand - state.position)
    if v_cmd > max_velocity:
        v_cmd = max_velocity
    elif v_cmd < -max_velocity:
        v_cmd = -max_velocity
    friction = params.viscous_friction * state.velocity * r  # N·m
    # Acceleration (counts/s²) reachable with the current limit, net of friction.
    a_cmd = (v_cmd - state.velocity) / dt
    torque = params.inertia * a_cmd * r + friction
    torque_max = params.torque_constant * max_current
    if torque > torque_max:
        torque = torque_max
    elif torque < -torque_max:
        torque = -torque_max
    accel = (torque - friction) / (params.inertia * r)
    state.velocity += accel * dt
    state.position += state.velocity * dt
    state.current = torque / params.torque_constant


def step_coast(params: MotorParams, state: MotorState, dt: float) -> None:
    """Advance one step with the power stage off: no torque, the rotor coasts down."""
    state.current = 0.0
    if state.jammed:
        state.velocity = 0.0
        return
    state.velocity *= math.exp(-dt / params.coast_time_constant)
    if abs(state.velocity) < 1e-3:
        state.velocity = 0.0
    state.position += state.velocity * dt
