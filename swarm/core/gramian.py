"""Copies of the weighted observability Gramian with forgetting (SPEC §6, thesis 3.4, 3.29)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def initial_gramian(epsilon: float) -> Array:
    """G_ir(0) = 2εI (SPEC §6, thesis Chapter 4)."""
    return 2.0 * epsilon * np.eye(3)


def gramian_step(
    gramian: Array,
    projector_mean: Array,
    neighbour_gramians: Sequence[Array],
    *,
    n_agents: int,
    forgetting: float,
    info_gain: float,
    consensus_gain: float,
    dt_s: float,
) -> Array:
    """Euler step of Ġ_ir = −ρG_ir + bN s_ir + Σ_j (G_jr − G_ir), then symmetrize (3.29).

    ``projector_mean`` is s_ir, the consensus estimate of (1/N)Σ_j w_jr Π̂_jr; works on a
    single 3×3 copy or a stack of them.
    """
    coupling = np.zeros_like(gramian)
    for g_j in neighbour_gramians:
        coupling += g_j - gramian
    rate = (-forgetting * gramian + (info_gain * n_agents) * projector_mean
            + consensus_gain * coupling)
    updated = gramian + dt_s * rate
    return 0.5 * (updated + np.swapaxes(updated, -1, -2))


def true_gramian_step(
    gramian: Array, information_rate: Array, *, forgetting: float, dt_s: float
) -> Array:
    """Euler step of the centralized Ġ = −ρG + bΣ_i w_iΠ_i (3.4), used for checking."""
    return gramian + dt_s * (-forgetting * gramian + information_rate)
