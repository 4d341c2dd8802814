"""Where one drone's consensus states live in its packed vector (SPEC §6).

The agent advances every consensus state of every target in one operation
(``agent._consensus_operator``), so it keeps them in one vector x, in this order:

    x = [ s: wΠ̂ (9M) | s: w (M) | η: wΠ̂ (9M) | η: w (M) | G (9M) ]

with each 3×3 block row-major, target by target: s the PI consensus estimates of (1/N)Σ w Π̂
and (1/N)Σ w (3.30), η their integrals, G the Gramian copies (3.29). The local input
u = [wΠ̂, w] is laid out as s. This module is the only place that knows the offsets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ConsensusLayout:
    """The slices of x for M targets (module docstring)."""

    n_targets: int
    size: int = field(init=False)  # 29M
    projector_mean: slice = field(init=False)  # s of wΠ̂
    weight_mean: slice = field(init=False)  # s of w
    projector_integral: slice = field(init=False)  # η of wΠ̂
    weight_integral: slice = field(init=False)  # η of w
    gramian: slice = field(init=False)  # G
    means: slice = field(init=False)  # s, laid out as the local input u
    integrals: slice = field(init=False)  # η

    def __post_init__(self) -> None:
        m = self.n_targets
        for name, start, stop in (("size", 29 * m, None),
                                  ("projector_mean", 0, 9 * m), ("weight_mean", 9 * m, 10 * m),
                                  ("projector_integral", 10 * m, 19 * m),
                                  ("weight_integral", 19 * m, 20 * m),
                                  ("gramian", 20 * m, 29 * m), ("means", 0, 10 * m),
                                  ("integrals", 10 * m, 20 * m)):
            object.__setattr__(self, name, start if stop is None else slice(start, stop))

    def target_projector_mean(self, target: int) -> slice:
        """s of wΠ̂ for one target, its 9 entries row-major."""
        return slice(9 * target, 9 * target + 9)

    def pack(self, projector_mean: Array, weight_mean: Array, projector_integral: Array,
             weight_integral: Array, gramian: Array) -> tuple[Array, ...]:
        """The parts of x in order, flat (``np.concatenate`` makes x of them)."""
        return (projector_mean.ravel(), weight_mean, projector_integral.ravel(),
                weight_integral, gramian.ravel())

    def unpack(self, x: Array) -> dict[str, Array]:
        """Each state of x by name, (M, 3, 3) or (M,), as views of x."""
        m = self.n_targets
        return {"projector_mean": x[self.projector_mean].reshape(m, 3, 3),
                "weight_mean": x[self.weight_mean],
                "projector_integral": x[self.projector_integral].reshape(m, 3, 3),
                "weight_integral": x[self.weight_integral],
                "gramian": x[self.gramian].reshape(m, 3, 3)}
