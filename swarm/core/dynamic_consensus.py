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


def switching_pi_consensus_step(
    estimate: Array,
    integral: Array,
    local_input: Array,
    neighbour_estimates: Sequence[Array],
    gains: ConsensusGains,
    dt_s: float,
) -> tuple[Array, Array]:
    """One Euler step of the PI consensus for a graph that changes (docs/network.md):
    ṡ_i = −ζ s_i − K_p Σ_j (s_i − s_j) + K_i η_i + ζ u_i, η̇_i = −K_i Σ_j (s_i − s_j).

    The integral enters as it is, where (3.30) takes its differences with the neighbours'.
    Σ_i η_i stays 0 on any symmetric graph, so the mean of s low-pass-tracks the mean of the
    inputs; at rest η_i = −ζ(u_i − ū)/K_i, which does not depend on the graph, so a link
    that comes or goes leaves η where it is needed (3.30's η_i − η_j settle to values that
    belong to the graph they were integrated on).
    """
    disagreement = np.zeros_like(estimate)
    for s_j in neighbour_estimates:
        disagreement += estimate - s_j
    estimate_rate = (gains.zeta * (local_input - estimate) - gains.kp * disagreement
                     + gains.ki * integral)
    return estimate + dt_s * estimate_rate, integral - dt_s * gains.ki * disagreement
