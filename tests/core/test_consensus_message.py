"""The consensus message as one packed block (``swarm.core.consensus_message``): ``of_arrays``
packs, the named arrays are views of what was packed, the states part is the agent's own
packed consensus state, and arrays that do not make a message are refused by name."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.consensus_message import (
    ARRAY_NAMES,
    PAIR_NAMES,
    STATE_NAMES,
    ConsensusMessage,
    ConsensusMessageError,
    array_shapes,
    message_layout,
    message_size,
)
from swarm.core.params import ControlParams

from .test_drone_step import lone_agent


@settings(max_examples=100, deadline=None)
@given(m=st.integers(1, 4), n=st.sampled_from([3, 6]), with_states=st.booleans(),
       seed=st.integers(0, 2**32 - 1))
def test_of_arrays_packs_and_the_names_give_back_every_array_bit_for_bit(
        m: int, n: int, with_states: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    shapes = array_shapes(m, n)
    arrays = {name: rng.normal(size=shapes[name]) * 10.0 ** rng.integers(-300, 300)
              for name in (ARRAY_NAMES if with_states else PAIR_NAMES)}
    states = {name: arrays[name] for name in STATE_NAMES} if with_states else {}
    message = ConsensusMessage.of_arrays(4, 9, 0, arrays["information"],
                                         arrays["information_vector"], **states)
    assert (message.sender, message.step, message.round) == (4, 9, 0)
    assert (message.n_targets, message.n_state) == (m, n)
    assert message.data.shape == (message_size(m, n, with_states),)
    assert message.data.dtype == np.float64 and message.has_states == with_states
    assert set(message.arrays()) == set(arrays)
    for name in ARRAY_NAMES:
        got = getattr(message, name)
        if name not in arrays:
            assert got is None and message.array(name) is None
            continue
        assert got.tobytes() == arrays[name].tobytes(), name  # bit for bit, C order
        assert np.shares_memory(got, message.data), name  # a view, not a copy
        assert message.arrays()[name].tobytes() == got.tobytes()
    # The layout is the packing: consecutive, in ARRAY_NAMES order, filling data exactly.
    layout = message_layout(m, n, with_states)
    assert [name for name, *_ in layout] == list(ARRAY_NAMES if with_states else PAIR_NAMES)
    assert all(a[3] == b[2] for a, b in itertools.pairwise(layout))


def test_the_states_part_of_a_round_0_message_is_the_agents_packed_state() -> None:
    """The agent makes its round-0 message by one concatenation: [ICF pair | consensus
    state], so the named states must be where ``ConsensusLayout`` keeps them."""
    agent = lone_agent(ControlParams())
    message = agent.begin_step(0, np.array([0.5, -0.2, 3.0]), [])
    pair = message.information.size + message.information_vector.size
    layout = ConsensusLayout(1)
    state = message.data[pair:]
    assert state.size == layout.size
    for name in STATE_NAMES:
        view = getattr(message, name)
        np.testing.assert_array_equal(view.ravel(), state[getattr(layout, name)], err_msg=name)
    np.testing.assert_array_equal(message.gramian[0], 2 * 0.05 * np.eye(3))


@pytest.mark.parametrize(("arrays", "words"), [
    (dict(information=None), "information has shape (), expected (M, n, n)"),
    (dict(information=np.zeros((2, 6, 5))), "information has shape (2, 6, 5)"),
    (dict(information_vector=np.zeros((2, 5))), "information_vector has shape (2, 5), expected "
                                                "(2, 6)"),
    (dict(gramian=None), "round-0 consensus states incomplete: gramian missing"),
    (dict(weight_mean=np.zeros(3)), "weight_mean has shape (3,), expected (2,)"),
    (dict(weight_mean=np.array(["a", "b"])), "weight_mean is not numbers: ValueError"),
])
def test_arrays_that_do_not_make_a_message_are_refused_by_name(arrays: dict, words: str
                                                              ) -> None:
    shapes = array_shapes(2, 6)
    given = {name: np.ones(shapes[name]) for name in ARRAY_NAMES} | arrays
    with pytest.raises(ConsensusMessageError) as info:
        ConsensusMessage.of_arrays(0, 0, 0, given.pop("information"),
                                   given.pop("information_vector"), **given)
    assert words in str(info.value)
    with pytest.raises(KeyError, match="no array 'velocity'"):
        ConsensusMessage.of_arrays(0, 0, 1, np.ones((1, 3, 3)), np.ones((1, 3))).array("velocity")
