# The interface of swarm/agent/_exchange.c (its methods table and PyInit__exchange), for mypy.
from collections.abc import Sequence
from typing import Any

import numpy as np
from _typeshed import ReadableBuffer
from numpy.typing import NDArray

CARRY_FIELDS: tuple[tuple[str, int, int], ...]

# rows: any C-contiguous float64 buffer (an array, or a message's bytes cast to "d").
def nearby(rows: NDArray[np.float64] | memoryview[Any], width: int, ids: Sequence[int] | None,
           skip: int, carry: Sequence[float] | None, around: Sequence[float] | None,
           radius: float, always: ReadableBuffer, /) -> dict[int, list[float]]: ...
