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

import dataclasses
import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from swarm.core import kernels
from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.drone_step import AgentSetup, DroneAgent, _consensus_operator, consensus_step
from swarm.core.dynamic_consensus import pi_consensus_step
from swarm.core.formation import (
    bearing_error,
    bearing_formation_scalars,
    bearing_formation_velocity,
)
from swarm.core.gramian import gramian_step
from swarm.core.icf import consensus_iteration
from swarm.core.params import (
    ConsensusGains,
    ControlParams,
    EstimationParams,
    GramianParams,
    PerceptionParams,
)

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
    parts = {"state": own, "disagreement": disagreement, "input": local_input, "zero": [0.0]}
    z = np.concatenate([parts[name] for name in kernels.CONSENSUS_STEP_Z])
    packed = consensus_step((index, coefficients), own, disagreement, local_input.tolist())
    # The compiled sum is numpy's gather-product-sum, bit for bit.
    assert packed.tobytes() == np.add.reduce(z[index] * coefficients, axis=0).tobytes()
    fast = layout.unpack(packed)

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


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_neighbours=st.integers(1, 4),
       poisoned=st.sampled_from([None, "nan", "inf"]), m=st.integers(1, 3))
def test_the_agents_consensus_round_is_consensus_iteration_bit_for_bit(
        seed: int, n_neighbours: int, poisoned: str | None, m: int) -> None:
    """``DroneAgent.consensus_round`` (the compiled ``consensus_sums`` on the packed blocks
    as they came) against ``icf.consensus_iteration`` of the ICF pair, bit for bit, and the
    round-0 disagreement against Σ_j (x_i − x_j) of the consensus states, over two rounds;
    a neighbour whose block holds a non-finite number is left out of both and counted."""
    rng = np.random.default_rng(seed)
    neighbours = list(range(1, n_neighbours + 1))
    weights = {j: float(w) for j, w in zip(neighbours, rng.uniform(0.05, 0.3, n_neighbours),
                                           strict=True)}
    setup = AgentSetup(
        drone_id=0, n_drones=n_neighbours + 1, n_targets=m, dt_s=0.02,
        neighbour_weights=weights, perception=PerceptionParams(),
        estimation=EstimationParams(consensus_rounds=2), gramian=GramianParams(),
        control=ControlParams())
    agent = DroneAgent(setup, rng.normal(size=(m, 3)))
    message = agent.begin_step(0, np.array([0.3, -0.1, 3.0]), [])
    bad = int(rng.choice(neighbours)) if poisoned else None
    for rnd in (0, 1):
        before = agent.snapshot()
        own_pair, own_states = before.icf_pair, before.consensus_states
        blocks = {j: rng.normal(size=message.data.shape) * 10.0 ** rng.integers(-3, 4)
                  for j in neighbours}
        if bad is not None:
            blocks[bad][rng.integers(blocks[bad].size if rnd == 0 else own_pair.size)] = (
                np.nan if poisoned == "nan" else -np.inf)
        inbox = {j: dataclasses.replace(message, sender=j, data=blocks[j]) for j in neighbours}
        message = agent.consensus_round(inbox) or message
        after = agent.snapshot()
        used = [j for j in neighbours if j != bad]
        expected = consensus_iteration(own_pair, [(weights[j], blocks[j][:own_pair.size])
                                                  for j in used])
        assert after.icf_pair.tobytes() == expected.tobytes()
        assert after.rejected_this_step - before.rejected_this_step == (bad is not None)
        if rnd == 0:
            differences = [own_states - blocks[j][own_pair.size:] for j in used]
            np.testing.assert_array_equal(
                after.disagreement, sum(differences[1:], differences[0]) if used
                else np.zeros_like(own_states))
