"""Bearing-only formation control, the nominal task of Case 3 (SPEC §10, Zhao & Zelazo 2015)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from swarm.core.projector import bearing, projector

Array = NDArray[np.float64]


def circle_bearings(n_drones: int) -> Array:
    """Desired bearings g*_ij (N×N×3) of a planar circle, drone i at angle 2πi/N (SPEC §10)."""
    angles = 2.0 * np.pi * np.arange(n_drones) / n_drones
    points = np.stack((np.cos(angles), np.sin(angles), np.zeros(n_drones)), axis=1)
    desired = np.zeros((n_drones, n_drones, 3))
    for i in range(n_drones):
        for j in range(n_drones):
            if i != j:
                desired[i, j] = bearing(points[j] - points[i])[0]
    return desired


def bearing_formation_velocity(
    own_position: Array,
    neighbour_positions: Mapping[int, Array],
    desired_bearings: Mapping[int, Array],
    gain: float,
) -> Array:
    """u_d,i = −k_f Σ_j P_{g_ij} g*_ij over the neighbours whose position is known (SPEC §10)."""
    velocity = np.zeros(3)
    for j, position in neighbour_positions.items():
        g_ij, _ = bearing(position - own_position)
        velocity -= projector(g_ij) @ desired_bearings[j]
    return gain * velocity


def bearing_error(
    own_position: Array,
    neighbour_positions: Mapping[int, Array],
    desired_bearings: Mapping[int, Array],
) -> float:
    """e_β,i = (1/|N_i|) Σ_j ‖g_ij − g*_ij‖ (SPEC §10, thesis Fig. 4.17)."""
    if not neighbour_positions:
        return 0.0
    total = 0.0
    for j, position in neighbour_positions.items():
        g_ij, _ = bearing(position - own_position)
        total += float(np.linalg.norm(g_ij - desired_bearings[j]))
    return total / len(neighbour_positions)
