"""The command reference: the thesis' single integrator run along the agent's commands.

The barriers of SPEC §8 assume each drone flies exactly its command, ṗ_i = u_i. A real
autopilot following velocity setpoints only integrates its own velocity errors into
position drift (PX4 SIH drifted 0.2-0.6 m/s at a zero setpoint while its estimator said ~0).
Sent instead the trajectory the single integrator would fly,

    r_k = r_(k−1) + Δt_k·u_(k−1),   setpoint_k = (r_k, u_k, (u_k − u_(k−1))/Δt_k),

Δt_k the time since the last setpoint (ΔT in lockstep; measured in realtime, so a late step
does not leave the reference behind the vehicle),

(position, velocity feed-forward and acceleration feed-forward), the autopilot's position
loop removes that bias: it flies v = u + K_p(r − p) and so follows the reference, not only
its slope. r starts at the vehicle's position at the first command and is put back there
when the vehicle is farther than ``reset_distance_m`` from it (it could not follow: a
failsafe, a collision row released, a wind gust), so the position loop never pulls across
the swarm to catch up; every reset is counted.

The agent measures the tracking error each step: ‖p − r‖ against the reference and
‖v − u_(k−1)‖ of the vehicle's velocity against the command it was flying (the ē of
``barrier.robust_lower_bound`` bounds the latter). Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class TrackedSetpoint:
    """One setpoint along the reference, in W (metres, m/s, m/s²)."""

    position_w: Vec3
    velocity_w: Vec3
    acceleration_w: Vec3
    reset: bool  # the reference was put back on the vehicle this step
    position_error_m: float  # ‖p − r‖ before any reset
    velocity_error_m_s: float | None  # ‖v − u_(k−1)‖; None: no earlier command or no v


class CommandReference:
    """r_k of the single integrator ṙ = u, with its resets (module doc)."""

    def __init__(self, reset_distance_m: float) -> None:
        if not (math.isfinite(reset_distance_m) and reset_distance_m > 0):
            raise ValueError(f"reset_distance_m must be a finite number > 0 "
                             f"(got {reset_distance_m!r})")
        self.reset_distance_m = float(reset_distance_m)
        self._position: Vec3 | None = None
        self._last_command: Vec3 | None = None
        self.resets = 0

    @property
    def position_w(self) -> Vec3 | None:
        return self._position

    def restart(self) -> None:
        """Forget the reference: the next setpoint starts it on the vehicle again (while the
        vehicle flies a mode of its own, the reference would only run away from it)."""
        self._position = self._last_command = None

    def setpoint(self, vehicle_position_w: Vec3, vehicle_velocity_w: Vec3 | None,
                 command_w: Vec3, elapsed_s: float) -> TrackedSetpoint:
        """The setpoint for ``command_w`` = u_k, ``elapsed_s`` = Δt_k after the last one (any
        value > 0 at the first, where r starts on the vehicle)."""
        if not (math.isfinite(elapsed_s) and elapsed_s > 0):
            raise ValueError(f"elapsed_s must be a finite number > 0 (got {elapsed_s!r})")
        p, last = vehicle_position_w, self._last_command
        if self._position is None or last is None:
            r, previous = p, command_w
        else:
            r0 = self._position
            r = (r0[0] + elapsed_s * last[0], r0[1] + elapsed_s * last[1],
                 r0[2] + elapsed_s * last[2])
            previous = last
        error = _distance(p, r)
        reset = error > self.reset_distance_m
        if reset:
            r = p
            self.resets += 1
        velocity_error = (None if last is None or vehicle_velocity_w is None
                          else _distance(vehicle_velocity_w, last))
        acceleration = ((command_w[0] - previous[0]) / elapsed_s,
                        (command_w[1] - previous[1]) / elapsed_s,
                        (command_w[2] - previous[2]) / elapsed_s)
        self._position, self._last_command = r, command_w
        return TrackedSetpoint(r, command_w, acceleration, reset, error, velocity_error)


def _distance(a: Vec3, b: Vec3) -> float:
    dx, dy, dz = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)
