"""Ground-target trajectories (SPEC §11): analytic, so the truth is exact at every step.

Targets start at rest and reach their velocity through a raised-cosine ramp over ``ramp_s``:
r(τ) = ½(1 − cos(πτ/T)) for 0 < τ < T. ``ramp_distance`` S(τ) = ∫ r is the distance covered
per unit of final speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def ramp(elapsed_s: float, ramp_s: float) -> float:
    """r(τ): 0 before the start, raised cosine up to 1 over ``ramp_s``."""
    if elapsed_s <= 0.0:
        return 0.0
    if elapsed_s >= ramp_s:
        return 1.0
    return 0.5 * (1.0 - math.cos(math.pi * elapsed_s / ramp_s))


def ramp_distance(elapsed_s: float, ramp_s: float) -> float:
    """S(τ) = ∫_0^τ r: τ/2 − (T/2π) sin(πτ/T) during the ramp, τ − T/2 after it."""
    if elapsed_s <= 0.0:
        return 0.0
    if elapsed_s >= ramp_s:
        return elapsed_s - 0.5 * ramp_s
    # S = (T/2π)(x − sin x), x = πτ/T; near 0 the difference cancels, so use its series there.
    x = math.pi * elapsed_s / ramp_s
    x_minus_sin = x**3 / 6.0 * (1.0 - x * x / 20.0 * (1.0 - x * x / 42.0)) if x < 1e-2 else (
        x - math.sin(x))
    return ramp_s / (2.0 * math.pi) * x_minus_sin


class Trajectory(Protocol):
    def position(self, time_s: float) -> Array: ...

    def velocity(self, time_s: float) -> Array: ...


@dataclass(frozen=True)
class LinearTrajectory:
    """Straight line reaching ``velocity_m_s`` smoothly (Case 1, target 1 of Case 2)."""

    start_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]
    ramp_s: float = 5.0

    def position(self, time_s: float) -> Array:
        return np.array(self.start_m) + np.array(self.velocity_m_s) * ramp_distance(
            time_s, self.ramp_s)

    def velocity(self, time_s: float) -> Array:
        return np.array(self.velocity_m_s) * ramp(time_s, self.ramp_s)


@dataclass(frozen=True)
class SinusoidTrajectory:
    """p(t) = p0 + v_drift S(t) + a sin(ωt) (Case 2, target 2: a 2.2 m, 0.15 rad/s wave)."""

    start_m: tuple[float, float, float]
    drift_velocity_m_s: tuple[float, float, float]
    amplitude_m: tuple[float, float, float]
    angular_rate_rad_s: float
    ramp_s: float = 5.0

    def position(self, time_s: float) -> Array:
        return (np.array(self.start_m)
                + np.array(self.drift_velocity_m_s) * ramp_distance(time_s, self.ramp_s)
                + np.array(self.amplitude_m) * math.sin(self.angular_rate_rad_s * time_s))

    def velocity(self, time_s: float) -> Array:
        return (np.array(self.drift_velocity_m_s) * ramp(time_s, self.ramp_s)
                + np.array(self.amplitude_m) * self.angular_rate_rad_s
                * math.cos(self.angular_rate_rad_s * time_s))


@dataclass(frozen=True)
class OutAndBackTrajectory:
    """Out along ``velocity_m_s``, turn at ``turn_s``, back at rest at the start at ``back_s``.

    Velocity scale σ(t) = r(t) − (1 + k) r(t − t_turn) + k r(t − (t_back − T)), every change
    a raised-cosine ramp of length T; k = t_turn/(t_back − T − t_turn) makes the net
    displacement vanish, so the target ends where it started (Case 3).
    """

    start_m: tuple[float, float, float]
    velocity_m_s: tuple[float, float, float]
    turn_s: float
    back_s: float
    ramp_s: float = 5.0

    def __post_init__(self) -> None:
        # Start at rest at start_m, finish the turn before the final ramp, end at rest.
        if not (0 < self.ramp_s <= self.turn_s
                and self.turn_s + 2 * self.ramp_s < self.back_s < math.inf):
            raise ValueError(
                f"out_and_back needs 0 < ramp_s <= turn_s and turn_s + 2·ramp_s < back_s "
                f"(got turn_s={self.turn_s}, back_s={self.back_s}, ramp_s={self.ramp_s})")

    @property
    def return_speed_ratio(self) -> float:
        return self.turn_s / (self.back_s - self.ramp_s - self.turn_s)

    def _scale_integral(self, t: float) -> float:
        k, T = self.return_speed_ratio, self.ramp_s
        return (ramp_distance(t, T) - (1.0 + k) * ramp_distance(t - self.turn_s, T)
                + k * ramp_distance(t - (self.back_s - T), T))

    def _scale(self, t: float) -> float:
        k, T = self.return_speed_ratio, self.ramp_s
        return (ramp(t, T) - (1.0 + k) * ramp(t - self.turn_s, T)
                + k * ramp(t - (self.back_s - T), T))

    def position(self, time_s: float) -> Array:
        return np.array(self.start_m) + np.array(self.velocity_m_s) * self._scale_integral(time_s)

    def velocity(self, time_s: float) -> Array:
        return np.array(self.velocity_m_s) * self._scale(time_s)
