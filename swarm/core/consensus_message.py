"""What a drone sends its neighbours in one consensus round (SPEC §5-§6), as one flat block.

A message carries the sender's ICF information pair and, in round 0, its consensus states,
packed in one float64 vector ``data``, each array in C order:

    data = [ V (M·n·n) | v (M·n) ]                                    every round
         + [ s wΠ̂ (9M) | s w (M) | η wΠ̂ (9M) | η w (M) | G (9M) ]    round 0 only
         + [ reach stamps (N) ]                  round 0, on a range graph only

(the reach stamps: ``swarm.core.network.ReachTracker``, docs/network.md.)

The second part is the agent's own packed consensus state (``ConsensusLayout``) and the first
its packed ICF pair, so the agent makes a message by one concatenation, the wire sends
``data``'s bytes as they are (``swarm.messages.wire.ConsensusWire``) and makes a received
message of one copy, and the receiving agent stacks its neighbours' blocks as they come:
nothing is split into arrays and joined again on the way. The arrays by name are views of
``data`` (``information``, ``gramian``, …); ``ConsensusMessage.of_arrays`` packs them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.kernels import ICF_PAIR
from swarm.errors import VigilError

Array = NDArray[np.float64]

# The arrays of a message in packing order: the ICF pair as the agent's kernel packs it
# (``kernels.ICF_PAIR``: V, then v), then the consensus states in the order of
# ``ConsensusLayout``.
PAIR_NAMES: Final = ICF_PAIR
STATE_NAMES: Final = ("projector_mean", "weight_mean", "projector_integral", "weight_integral",
                      "gramian")
ARRAY_NAMES: Final = PAIR_NAMES + STATE_NAMES


class ConsensusMessageError(VigilError, ValueError):
    """Arrays that do not make a consensus message (shapes that disagree, only some of the
    round-0 states, values that are not numbers)."""


def array_shapes(n_targets: int, n_state: int) -> dict[str, tuple[int, ...]]:
    """The shape of each array of a message, in packing order."""
    m, n = n_targets, n_state
    return {"information": (m, n, n), "information_vector": (m, n),
            "projector_mean": (m, 3, 3), "weight_mean": (m,), "projector_integral": (m, 3, 3),
            "weight_integral": (m,), "gramian": (m, 3, 3)}


@functools.lru_cache(maxsize=64)
def message_layout(n_targets: int, n_state: int, with_states: bool
                   ) -> tuple[tuple[str, tuple[int, ...], int, int], ...]:
    """(name, shape, start, stop) of each array in ``data``, in floats: the ICF pair, then
    the states where the agent's packed state (``ConsensusLayout``) keeps them."""
    shapes = array_shapes(n_targets, n_state)
    layout: list[tuple[str, tuple[int, ...], int, int]] = []
    size = 0
    for name in PAIR_NAMES:
        layout.append((name, shapes[name], size, size + math.prod(shapes[name])))
        size = layout[-1][3]
    if with_states:
        states = ConsensusLayout(n_targets)
        layout += [(name, shapes[name], size + getattr(states, name).start,
                    size + getattr(states, name).stop) for name in STATE_NAMES]
    return tuple(layout)


def message_size(n_targets: int, n_state: int, with_states: bool) -> int:
    """Floats in ``data`` of a message with (round 0) or without the consensus states."""
    return message_layout(n_targets, n_state, with_states)[-1][3]


@dataclass(frozen=True)
class ConsensusMessage:
    """What drone ``sender`` sends its neighbours in round ``round`` of step ``step``: its ICF
    information pair (V^κ, v^κ) and, in round 0, its continuous-time consensus states at the
    start of the step (SPEC §6), packed in ``data`` (module docstring) for M = ``n_targets``
    targets and the ICF state dimension n = ``n_state``.

    Made by the agent, by the wire's decoder, or from separate arrays by ``of_arrays``. Those
    three give ``data`` as a 1-D native float64 array of one of the two sizes; a message made
    otherwise is checked where it is used (the receiving agent counts it rejected, the
    encoder refuses it).
    """

    sender: int
    step: int
    round: int
    n_targets: int  # M
    n_state: int  # n
    data: Array

    @classmethod
    def of_arrays(cls, sender: int, step: int, round: int, information: Any,
                  information_vector: Any, *, projector_mean: Any = None,
                  projector_integral: Any = None, weight_mean: Any = None,
                  weight_integral: Any = None, gramian: Any = None) -> ConsensusMessage:
        """The message of these arrays (V (M, n, n), v (M, n), and either all five consensus
        states or none), converted to float64 and packed. Raises ``ConsensusMessageError``
        naming the array that does not fit."""
        shape: tuple[int, ...] = np.shape(information) if information is not None else ()
        if len(shape) != 3 or shape[1] != shape[2]:
            raise ConsensusMessageError(f"information has shape {shape!s:.60}, expected "
                                        f"(M, n, n)")
        m, n = int(shape[0]), int(shape[1])
        states = {"projector_mean": projector_mean, "weight_mean": weight_mean,
                  "projector_integral": projector_integral, "weight_integral": weight_integral,
                  "gramian": gramian}
        missing = [name for name in STATE_NAMES if states[name] is None]
        if missing and len(missing) < len(STATE_NAMES):
            raise ConsensusMessageError("round-0 consensus states incomplete: "
                                        f"{', '.join(missing)} missing")
        given = {"information": information, "information_vector": information_vector,
                 **({} if missing else states)}
        layout = message_layout(m, n, not missing)
        data = np.empty(layout[-1][3])
        for name, expected, start, stop in layout:
            value = given[name]
            got = np.shape(value) if value is not None else ()
            if got != expected:
                raise ConsensusMessageError(f"{name} has shape {got!s:.60}, expected "
                                            f"{expected}")
            try:
                data[start:stop] = np.asarray(value, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise ConsensusMessageError(f"{name} is not numbers: {type(exc).__name__}: "
                                            f"{exc}") from None
        return cls(sender, step, round, m, n, data)

    @property
    def has_states(self) -> bool:
        """Whether the message carries the consensus states (round 0)."""
        size: int = self.data.shape[0]
        return size > self.n_targets * self.n_state * (self.n_state + 1)

    def array(self, name: str) -> Array | None:
        """The array ``name`` (one of ``ARRAY_NAMES``) as a view of ``data``, None for a state
        the message does not carry."""
        for field_name, shape, start, stop in message_layout(self.n_targets, self.n_state,
                                                             self.has_states):
            if field_name == name:
                return self.data[start:stop].reshape(shape)
        if name in STATE_NAMES:
            return None
        raise KeyError(f"a consensus message has no array {name!r}")

    def arrays(self) -> dict[str, Array]:
        """Every array the message carries, by name, as views of ``data``."""
        return {name: self.data[start:stop].reshape(shape) for name, shape, start, stop
                in message_layout(self.n_targets, self.n_state, self.has_states)}

    # The arrays by name, views of ``data`` (the states None after round 0).
    information = property(lambda self: self.array("information"), doc="V^κ, (M, n, n)")
    information_vector = property(lambda self: self.array("information_vector"),
                                  doc="v^κ, (M, n)")
    projector_mean = property(lambda self: self.array("projector_mean"),
                              doc="s for wΠ̂, (M, 3, 3)")
    weight_mean = property(lambda self: self.array("weight_mean"), doc="s for w, (M,)")
    projector_integral = property(lambda self: self.array("projector_integral"),
                                  doc="η for wΠ̂, (M, 3, 3)")
    weight_integral = property(lambda self: self.array("weight_integral"), doc="η for w, (M,)")
    gramian = property(lambda self: self.array("gramian"), doc="G copies, (M, 3, 3)")

    def is_finite(self) -> bool:
        return bool(np.isfinite(self.data).all())
