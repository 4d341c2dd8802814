"""PI dynamic average consensus, forward-Euler discretized (SPEC §6, thesis 3.30).

ṡ_i = −ζ s_i − K_p Σ_j (s_i − s_j) + K_i Σ_j (η_i − η_j) + ζ u_i,
η̇_i = −K_i Σ_j (s_i − s_j).
Summed over the network, the couplings cancel, so the mean of s low-pass-tracks the mean of
the inputs whatever the initial state; K_p and K_i remove the disagreement.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from swarm.core.params import ConsensusGains

Array = NDArray[np.float64]


def pi_consensus_step(
    estimate: Array,
    integral: Array,
    local_input: Array,
    neighbour_estimates: Sequence[Array],
    neighbour_integrals: Sequence[Array],
    gains: ConsensusGains,
    dt_s: float,
) -> tuple[Array, Array]:
    """One Euler step of (3.30) for drone i; arrays of any (matching) shape.

    Only the neighbours whose data is at hand are passed; the sums run over them.
    """
    disagreement = np.zeros_like(estimate)
    integral_gap = np.zeros_like(integral)
    for s_j, eta_j in zip(neighbour_estimates, neighbour_integrals, strict=True):
        disagreement += estimate - s_j
        integral_gap += integral - eta_j
    estimate_rate = (
        gains.zeta * (local_input - estimate) - gains.kp * disagreement + gains.ki * integral_gap
    )
    integral_rate = -gains.ki * disagreement
    return estimate + dt_s * estimate_rate, integral + dt_s * integral_rate
