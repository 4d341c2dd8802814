# The interface of swarm/agent/_exchange.c (its methods table and PyInit__exchange), for mypy.
from collections.abc import Sequence

import numpy as np
from _typeshed import ReadableBuffer
from numpy.typing import NDArray

CARRY_FIELDS: tuple[tuple[str, int, int], ...]

def nearby(rows: NDArray[np.float64], width: int, ids: Sequence[int] | None, skip: int,
           carry: Sequence[float] | None, around: Sequence[float] | None, radius: float,
           always: ReadableBuffer, /) -> dict[int, list[float]]: ...
