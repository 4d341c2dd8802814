"""Parity of the plain-float and packed fast paths the agent's step runs in Python with the
readable forms the finite-difference tests check (issue 15, point 1):
``bearing_formation_scalars`` ↔ ``bearing_formation_velocity`` / ``bearing_error``, and the
agent's packed consensus operator ↔ ``pi_consensus_step`` and ``gramian_step``. (The compiled
kernels' parity: ``test_kernels.py``.)

Tolerance: both forms evaluate the same formulas in a different order, so they agree to
round-off: 1e-9 of each quantity's scale (measured over these examples: 4e-16 for the
formation); a factor of 1.0001 on one coefficient of the consensus operator fails it.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from swarm.core.agent import _consensus_operator
from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.dynamic_consensus import pi_consensus_step
from swarm.core.formation import (
    bearing_error,
    bearing_formation_scalars,
    bearing_formation_velocity,
)
from swarm.core.gramian import gramian_step
from swarm.core.params import ConsensusGains, GramianParams

RTOL = 1e-9
EXAMPLES = settings(max_examples=300, deadline=None)

ANGLES = st.floats(0.0, 2.0 * math.pi)
COORDS = st.floats(-5.0, 5.0)


def _close(fast, readable, scale: float | None = None) -> None:
    fast, readable = np.asarray(fast, dtype=float), np.asarray(readable, dtype=float)
    size = max(float(np.max(np.abs(readable))), 1e-300) if scale is None else scale
    np.testing.assert_allclose(fast, readable, rtol=0.0, atol=RTOL * size)


@EXAMPLES
@given(st.tuples(COORDS, COORDS, COORDS),
       st.lists(st.tuples(st.tuples(COORDS, COORDS, COORDS), ANGLES, ANGLES), max_size=5),
       st.floats(0.1, 3.0))
def test_bearing_formation_scalars_equal_the_array_forms(own, neighbours, gain) -> None:
    own_p = np.array(own)
    positions, desired, listed = {}, {}, []
    for j, (offset, azimuth, elevation) in enumerate(neighbours):
        assume(float(np.linalg.norm(offset)) > 0.05)  # a neighbour is never on top of us
        position = own_p + np.array(offset)
        g_star = np.array([math.cos(elevation) * math.cos(azimuth),
                           math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        positions[j], desired[j] = position, g_star
        listed.append((tuple(position), tuple(g_star)))
    velocity, error = bearing_formation_scalars(own, listed, gain)
    _close(velocity, bearing_formation_velocity(own_p, positions, desired, gain), gain)
    _close(error, bearing_error(own_p, positions, desired), 1.0)


# -- the packed consensus operator ------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 3), n_neighbours=st.integers(0, 4),
       dt=st.floats(0.005, 0.1), rate_gain=st.floats(0.1, 20.0),
       forgetting=st.floats(0.05, 2.0), coupling=st.floats(0.1, 3.0))
def test_consensus_operator_equals_the_pi_consensus_and_gramian_steps(
        seed, m, n_neighbours, dt, rate_gain, forgetting, coupling) -> None:
    """The agent's packed consensus step (``_consensus_operator``: one gather, one product,
    one sum over z = [x, Σ_j (x − x_j), u, 0]) against ``pi_consensus_step`` (3.30) for wΠ̂
    and w with their own gains, and ``gramian_step`` (3.29) for the Gramian copies, whose
    source term is the consensus estimate s before the step."""
    rng = np.random.default_rng(seed)
    gram = GramianParams(forgetting=forgetting, consensus_gain=coupling,
                         projector_consensus=ConsensusGains(*rng.uniform(0.5, 10.0, 3)),
                         weight_consensus=ConsensusGains(*rng.uniform(0.5, 10.0, 3)))
    layout = ConsensusLayout(m)
    own = rng.normal(size=layout.size)
    others = [rng.normal(size=layout.size) for _ in range(n_neighbours)]
    local_input = rng.normal(size=10 * m)
    index, coefficients = _consensus_operator(layout, dt, gram, rate_gain)
    disagreement = sum((own - x for x in others), np.zeros(layout.size))
    z = np.concatenate((own, disagreement, local_input, [0.0]))
    fast = layout.unpack(np.add.reduce(z[index] * coefficients, axis=0))

    mine, theirs = layout.unpack(own), [layout.unpack(x) for x in others]
    new_s_p, new_eta_p = pi_consensus_step(
        mine["projector_mean"], mine["projector_integral"],
        local_input[:9 * m].reshape(m, 3, 3), [x["projector_mean"] for x in theirs],
        [x["projector_integral"] for x in theirs], gram.projector_consensus, dt)
    new_s_w, new_eta_w = pi_consensus_step(
        mine["weight_mean"], mine["weight_integral"], local_input[9 * m:],
        [x["weight_mean"] for x in theirs], [x["weight_integral"] for x in theirs],
        gram.weight_consensus, dt)
    new_g = gramian_step(mine["gramian"], mine["projector_mean"],
                         [x["gramian"] for x in theirs], n_agents=1, forgetting=forgetting,
                         info_gain=rate_gain, consensus_gain=coupling, dt_s=dt)
    scale = max(1.0, float(np.max(np.abs(z)))) * (1 + n_neighbours)
    for name, readable in (("projector_mean", new_s_p), ("weight_mean", new_s_w),
                           ("projector_integral", new_eta_p), ("weight_integral", new_eta_w),
                           ("gramian", new_g)):
        _close(fast[name], readable, scale)
