"""numpy's LAPACK gufuncs called directly on float64 stacks (internal, for the per-step path).

``np.linalg.inv`` and ``np.linalg.eigh`` run the same gufuncs as below behind a Python layer
(type resolution, an ``errstate`` context, error translation) that costs two to three times
the factorization itself on 3×3 and 6×6 matrices. The gufuncs signal a failure by filling the
result with NaN; the wrappers here check for it and then call the public function, which
raises the same ``LinAlgError`` as before, so only successful calls take the short path and
results are the same routine's. If numpy ever moves the private module, the public functions
are used.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

try:
    from numpy.linalg import _umath_linalg

    _inv = _umath_linalg.inv
    _cholesky = _umath_linalg.cholesky_lo  # what np.linalg.cholesky(a) runs
    _eigh = _umath_linalg.eigh_lo  # what np.linalg.eigh(a) (UPLO="L") runs
except (ImportError, AttributeError):  # pragma: no cover - depends on the numpy build
    _inv = _cholesky = _eigh = None


def positive_definite(stack: Array) -> bool:
    """Whether ``np.linalg.cholesky(stack)`` succeeds, i.e. every matrix is (numerically)
    positive definite."""
    if _cholesky is None:  # pragma: no cover
        try:
            np.linalg.cholesky(stack)
        except np.linalg.LinAlgError:
            return False
        return True
    with np.errstate(invalid="ignore"):  # a failed factorization is NaN-filled, not raised
        factor = _cholesky(stack)
    return math.isfinite(np.add.reduce(factor, axis=None))


def inv(stack: Array) -> Array:
    """``np.linalg.inv`` of a float64 stack of invertible matrices (e.g. positive definite)."""
    if _inv is None:  # pragma: no cover
        return np.linalg.inv(stack)
    result = _inv(stack)
    if not math.isfinite(np.add.reduce(result, axis=None)):
        # NaN-filled (singular) or overflowing: the public call raises or returns the same.
        return np.linalg.inv(stack)
    return result


def inv_positive_definite(stack: Array) -> Array:
    """``np.linalg.inv`` of a stack the caller knows to be positive definite (e.g. after
    ``positive_definite``, or built as one): no failure check."""
    if _inv is None:  # pragma: no cover
        return np.linalg.inv(stack)
    return _inv(stack)


def eigh(stack: Array) -> tuple[Array, Array]:
    """``np.linalg.eigh`` of a float64 stack of symmetric matrices (lower triangle used)."""
    if _eigh is None:  # pragma: no cover
        return np.linalg.eigh(stack)
    values, vectors = _eigh(stack)
    if not math.isfinite(np.add.reduce(values, axis=None)):
        return np.linalg.eigh(stack)
    return values, vectors
