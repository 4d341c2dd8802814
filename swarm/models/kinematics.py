"""Drone motion: the thesis' single integrator with box velocity bounds (SPEC §1, thesis
1.1), and an optional velocity response of a real autopilot (first-order lag with an
acceleration limit) that the emulated vehicles and the in-process reference share."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarm.errors import UsageError

Array = NDArray[np.float64]


def clamp_velocity(velocity_m_s: Array, u_max_m_s: float) -> Array:
    """|u_k| ≤ u_max per component; a non-finite command is treated as zero (hold)."""
    velocity = np.asarray(velocity_m_s, dtype=np.float64)
    if velocity.shape != (3,):
        if not np.all(np.isfinite(velocity)):
            return np.zeros(velocity.shape)
        return np.clip(velocity, -u_max_m_s, u_max_m_s)
    # A 3-vector on floats: what every vehicle does per setpoint and per tick, where numpy's
    # isfinite/all/clip cost ten times the arithmetic.
    x, y, z = velocity.tolist()
    if (x - x) + (y - y) + (z - z) != 0.0:  # x − x is NaN for ±inf and NaN
        return np.zeros(3)
    low = -u_max_m_s
    return np.array([low if x < low else u_max_m_s if x > u_max_m_s else x,
                     low if y < low else u_max_m_s if y > u_max_m_s else y,
                     low if z < low else u_max_m_s if z > u_max_m_s else z])


def step_drone(position_m: Array, velocity_m_s: Array, u_max_m_s: float, dt_s: float) -> Array:
    """p(k+1) = p(k) + ΔT·clamp(u) (forward Euler, SPEC §1)."""
    return position_m + dt_s * clamp_velocity(velocity_m_s, u_max_m_s)


@dataclass(frozen=True)
class VelocityResponse:
    """How a vehicle's velocity v follows its velocity command u (a real autopilot's velocity
    loop as seen from outside; the thesis' vehicle is ideal, v = u).

    Per step of length ΔT, with u already clamped to the box bound:

        Δ = (1 − e^(−ΔT/τ)) · (u − v_k)          (exact discretisation of τ·v̇ = u − v)
        v_(k+1) = v_k + Δ · min(1, a_max·ΔT / ‖Δ‖)  (acceleration limit on the vector)
        p_(k+1) = p_k + ΔT · v_(k+1)

    ``time_constant_s`` τ = 0 means no lag and ``accel_limit_m_s2`` a_max = 0 no limit; with
    both zero the response is ideal and ``step`` returns u itself (bit for bit the thesis'
    p_(k+1) = p_k + ΔT·u).
    """

    time_constant_s: float = 0.0
    accel_limit_m_s2: float = 0.0

    def __post_init__(self) -> None:
        for name in ("time_constant_s", "accel_limit_m_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0 (got {value})")

    @property
    def ideal(self) -> bool:
        return self.time_constant_s == 0.0 and self.accel_limit_m_s2 == 0.0

    def step(self, velocity_m_s: Array, command_m_s: Array, dt_s: float) -> Array:
        """v_(k+1) from v_k = ``velocity_m_s`` and the (clamped) command u (see the class)."""
        command = np.asarray(command_m_s, dtype=np.float64)
        if self.ideal:
            return command.copy()
        velocity = np.asarray(velocity_m_s, dtype=np.float64)
        gain = 1.0 if self.time_constant_s == 0.0 else -math.expm1(-dt_s / self.time_constant_s)
        change = gain * (command - velocity)
        if self.accel_limit_m_s2 > 0.0:
            largest = self.accel_limit_m_s2 * dt_s
            norm = math.sqrt(float(change @ change))
            if norm > largest:
                change = change * (largest / norm)
        return velocity + change


# Fitted to ArduCopter SITL (the build in ../shared/autopilots, copter.parm defaults) by
# benchmarks/fit_vehicle_response.py: two runs of a 205 s sequence of velocity setpoints at
# 50 Hz (steps 0.5-3 m/s, reversals, vertical ±1 m/s, a smooth swarm-like stretch), the last
# 86 s held out; both runs gave τ = 0.568 s, a_max = 1.65 m/s² (3-D fit), RMS velocity error
# 0.136 m/s horizontal on the fit (0.188 held out) against 0.735 (0.932) for the ideal
# v = u. docs/guarantee_real_vehicles.md, "The fit".
ARDUCOPTER_SITL_RESPONSE = VelocityResponse(time_constant_s=0.57, accel_limit_m_s2=1.65)
# Fitted to PX4 v1.15.4 SIH the same way (one run): τ = 0.95 s, a_max = 4.5 m/s², RMS 0.243
# m/s horizontal (0.270 held out) against 0.617 (0.738) ideal. Only roughly: PX4's horizontal
# velocity plateaus at ~0.76 of the command for seconds, a gain this model does not have.
PX4_SITL_RESPONSE = VelocityResponse(time_constant_s=0.95, accel_limit_m_s2=4.5)
IDEAL_RESPONSE = VelocityResponse()


def step_vehicle(position_m: Array, velocity_m_s: Array, command_m_s: Array, u_max_m_s: float,
                 dt_s: float, response: VelocityResponse) -> tuple[Array, Array]:
    """(p_(k+1), v_(k+1)) of a vehicle at p_k with velocity v_k told to fly ``command_m_s``:
    the command clamped (``clamp_velocity``), then ``response.step``, then p_k + ΔT·v_(k+1).
    With an ideal response this is ``step_drone``."""
    velocity = response.step(velocity_m_s, clamp_velocity(command_m_s, u_max_m_s), dt_s)
    return position_m + dt_s * velocity, velocity


class InitialPlacementError(UsageError, ValueError):
    """The start box cannot hold the drones at the requested separation."""


def sample_initial_positions(
    n_drones: int,
    center_m: Array,
    size_m: Array,
    min_separation_m: float,
    rng: np.random.Generator,
    max_tries: int = 10_000,
) -> Array:
    """Uniform positions in a box, resampled until every pair is ``min_separation_m`` apart.

    Raises InitialPlacementError if the box cannot hold that many drones that far apart.
    """
    center, size = np.asarray(center_m, float), np.asarray(size_m, float)
    if n_drones == 0:
        return np.zeros((0, 3))
    positions: list[Array] = []
    for _ in range(max_tries):
        candidate = center + (rng.random(3) - 0.5) * size
        if all(np.linalg.norm(candidate - p) >= min_separation_m for p in positions):
            positions.append(candidate)
            if len(positions) == n_drones:
                return np.array(positions)
    raise InitialPlacementError(
        f"could not place {n_drones} drones {min_separation_m} m apart in a box of size "
        f"{[float(v) for v in size]} m after {max_tries} tries; enlarge initial_box_size_m")
