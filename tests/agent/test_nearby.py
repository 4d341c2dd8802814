"""The exchange's compiled pass over the other drones (``swarm.agent.nearby``, ``_exchange.c``):
what it refuses, whom it keeps, and its carry in the order the C module exports. (Its
carry-forward, bit for bit against each beacon's formula, and the QP rows it leaves intact:
``test_exchange.py``.)"""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarm.agent import _exchange
from swarm.agent.nearby import CARRY_FIELDS, carry, nearby
from swarm.messages.wire import RELAY_WIDTH, BeaconRelayWire, BeaconWire


@pytest.mark.parametrize(("change", "error", "message"), [
    ({"rows": [0.0] * 6}, TypeError, "rows: expected a C-contiguous float64 array"),
    ({"rows": np.zeros(7)}, ValueError, "rows: 7 floats are not rows of 3"),
    ({"width": 2}, ValueError, "width 2"),
    ({"carry": [0.0] * 6}, ValueError, "width 3: expected >= 3 .8 with carry."),
    ({"ids": [0]}, ValueError, "ids: expected None or a list of 2 ints"),
    ({"ids": [1, -1]}, ValueError, r"ids\[1\]: drone -1 is negative"),
    ({"around": [0.0, 0.0]}, ValueError, "around: expected 3 floats"),
    ({"always": [1, 0]}, TypeError, "always: expected bytes"),
])
def test_nearby_names_what_it_was_given_wrong(change, error, message) -> None:
    args = {"rows": np.zeros(6), "width": 3, "ids": None, "skip": 0, "carry": None,
            "around": [0.0, 0.0, 0.0], "radius": 1.0, "always": b"\x00\x00"} | change
    with pytest.raises(error, match=message) as err:
        nearby(*args.values())
    assert "\n" not in str(err.value)


def test_nearby_keeps_the_drones_within_the_radius_the_marked_and_the_not_finite() -> None:
    rows = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [math.nextafter(1.0, 2.0), 0.0, 0.0],
                     [9.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [7.0, 0.0, 0.0]])
    got = nearby(rows, 3, None, 0, None, [0.0, 0.0, 0.0], 1.0, b"\x00\x00\x00\x01")
    assert list(got) == [1, 3, 4] and got[1] == [1.0, 0.0, 0.0]  # 5: past the marks
    assert nearby(rows, 3, [5, 4, 3, 2, 1, 0], 0, None, None, 1.0, b"").keys() == {
        5, 4, 3, 2, 1}


def test_the_carry_is_in_the_order_the_compiled_module_exports() -> None:
    """``carry`` puts each value in the field ``_exchange`` names for it, and the fields tile
    the carry."""
    assert CARRY_FIELDS is _exchange.CARRY_FIELDS
    assert [start for _, start, _ in CARRY_FIELDS] == [
        0, *(stop for _, _, stop in CARRY_FIELDS[:-1])]
    values = carry(0.5, 0.25, [1.0, 2.0, 3.0], 4.0)
    assert len(values) == CARRY_FIELDS[-1][2]
    assert {name: values[start:stop] for name, start, stop in CARRY_FIELDS} == {
        "relay_age": [0.5], "sample_age": [0.25], "flying": [1.0, 2.0, 3.0], "hold": [4.0]}


def test_nearby_carries_a_relay_row_forward_by_its_columns() -> None:
    """One relayed beacon through the wire's row and ``carry``: p + min(a_j + (relay age +
    held), hold) v − a_i v_i, and the hold when the beacon is older than it."""
    relay = BeaconRelayWire.build(3, [
        (BeaconWire.build(2, 3, 0.0, (1.0, 2.0, 3.0), velocity_m_s=(1.0, -2.0, 0.5),
                          sample_age_s=0.125), 0.25),
        (BeaconWire.build(5, 3, 0.0, (0.0, 0.0, 3.0), velocity_m_s=(0.0, 4.0, 0.0),
                          sample_age_s=2.0), 0.0)])
    got = nearby(relay.rows(), RELAY_WIDTH, [2, 5], 0, carry(0.5, 0.0625, [2.0, 0.0, -1.0], 1.0),
                 None, 0.0, b"")
    lead = 0.125 + (0.5 + 0.25)
    assert got[2] == [1.0 + lead * 1.0 - 0.0625 * 2.0, 2.0 + lead * -2.0,
                      3.0 + lead * 0.5 - 0.0625 * -1.0]
    assert got[5] == [0.0 - 0.0625 * 2.0, 0.0 + 1.0 * 4.0, 3.0 - 0.0625 * -1.0]
