# The interface of swarm/messages/_wire.c (its methods table and PyInit__wire), for mypy.
from collections.abc import Sequence

import numpy as np
from _typeshed import ReadableBuffer
from numpy.typing import NDArray

RELAY_FIELDS: tuple[tuple[str, int, int], ...]
RELAY_WIDTH: int

def native_finite(*parts: ReadableBuffer) -> bool: ...
def join_native(arrays: Sequence[NDArray[np.float64]],
                shapes: Sequence[tuple[int, ...]], /) -> bytes | None: ...
