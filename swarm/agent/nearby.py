"""The exchange's compiled pass over the other drones (``swarm/agent/_exchange.c``).

``nearby(rows, width, ids, skip, carry, around, radius, always) -> {id: [x, y, z]}``: the
other drones a step can use, as the core takes them (``swarm.agent.exchange``: ``Vicinity``,
``RealtimeExchange.beacons``), with the world's relay rows read by the wire's columns
(``swarm.messages.native.RELAY_*``) and ``carry`` built by ``carry`` in the order the module
exports. ``tests/agent/test_nearby.py`` and ``tests/agent/test_exchange.py`` bind it to each
relayed beacon's carry-forward formula computed alone, bit for bit, and to the QP rows the
core builds from every drone.

The extension is built by ``pip install -e .`` (setuptools, the machine's C compiler).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Final

from swarm.compiled import (
    Field,
    check_built_from_current_source,
    field_index,
    field_slice,
    not_built,
)
from swarm.messages.native import RELAY_ROW_HEADER

try:
    from swarm.agent import _exchange
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise not_built("swarm.agent._exchange", "swarm/agent/_exchange.c") from exc

check_built_from_current_source(Path(_exchange.__file__),
                                Path(__file__).with_name("_exchange.c"), RELAY_ROW_HEADER,
                                Path(__file__).parent.parent / "compiled.h")

nearby = _exchange.nearby

# ``nearby``'s carry: the relay's age, the own sample's age, the own velocity last sent (3),
# the longest a beacon is carried forward.
CARRY_FIELDS: Final[tuple[Field, ...]] = _exchange.CARRY_FIELDS
_RELAY_AGE: Final = field_index(CARRY_FIELDS, "relay_age")
_SAMPLE_AGE: Final = field_index(CARRY_FIELDS, "sample_age")
_FLYING: Final = field_slice(CARRY_FIELDS, "flying")
_HOLD: Final = field_index(CARRY_FIELDS, "hold")
_CARRY_SIZE: Final = CARRY_FIELDS[-1][2]


def carry(relay_age_s: float, sample_age_s: float, flying_m_s: Sequence[float],
          hold_s: float) -> list[float]:
    """``nearby``'s carry: each relayed position p_j carried forward as
    p_j + min(a_j + relay age + held_j, hold) v_j − a_i v_i, with a_i = ``sample_age_s`` and
    v_i = ``flying_m_s`` (the own velocity last sent)."""
    values = [0.0] * _CARRY_SIZE
    values[_RELAY_AGE] = relay_age_s
    values[_SAMPLE_AGE] = sample_age_s
    values[_FLYING] = flying_m_s
    values[_HOLD] = hold_s
    return values
