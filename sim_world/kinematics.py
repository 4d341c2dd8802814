"""Single-integrator drones with box velocity bounds (SPEC §1, thesis 1.1)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

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


class InitialPlacementError(ValueError):
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
