"""Bearing-only formation control, the nominal task of Case 3 (SPEC §10, Zhao & Zelazo 2015)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

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


def bearing_formation_scalars(
    own_position: Sequence[float],
    neighbours: Sequence[tuple[Sequence[float], Sequence[float]]],
    gain: float,
) -> tuple[tuple[float, float, float], float]:
    """``bearing_formation_velocity`` and ``bearing_error`` on plain floats, in one pass.

    ``neighbours`` lists (p_j, g*_ij) of the neighbours whose position is known, in the order
    the sums run. Same operations as the array versions up to round-off.
    """
    if not neighbours:
        return (0.0, 0.0, 0.0), 0.0
    px, py, pz = own_position
    ux = uy = uz = 0.0
    error = 0.0
    for (qx, qy, qz), (dx, dy, dz) in neighbours:
        rx, ry, rz = qx - px, qy - py, qz - pz
        distance = math.sqrt(rx * rx + ry * ry + rz * rz)
        gx, gy, gz = rx / distance, ry / distance, rz / distance
        # P_g g* = (I − g gᵀ) g*
        ux -= (1.0 - gx * gx) * dx + (0.0 - gx * gy) * dy + (0.0 - gx * gz) * dz
        uy -= (0.0 - gy * gx) * dx + (1.0 - gy * gy) * dy + (0.0 - gy * gz) * dz
        uz -= (0.0 - gz * gx) * dx + (0.0 - gz * gy) * dy + (1.0 - gz * gz) * dz
        ex, ey, ez = gx - dx, gy - dy, gz - dz
        error += math.sqrt(ex * ex + ey * ey + ez * ez)
    return (gain * ux, gain * uy, gain * uz), error / len(neighbours)
