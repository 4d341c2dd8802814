"""numpy's LAPACK gufuncs called directly on float64 stacks (internal, for the per-step path).

``np.linalg.cholesky``, ``inv`` and ``eigh`` run these same gufuncs behind a Python layer
(type resolution, an ``errstate`` context, error translation) that costs two to three times
the factorization itself on 3×3 and 6×6 matrices, so results are bit-identical to the public
calls. A gufunc signals a failure by filling its result with NaN: ``positive_definite`` turns
that into False (the caller then takes its pseudo-inverse path), ``eigh_lists`` into the
public call, which raises the same ``LinAlgError`` as before; ``inv_positive_definite`` is
only for matrices known to be positive definite. If numpy ever moves the private module, the
public functions are used.
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


def inv_positive_definite(stack: Array) -> Array:
    """``np.linalg.inv`` of a stack the caller knows to be positive definite (e.g. after
    ``positive_definite``, or built as one): no failure check."""
    if _inv is None:  # pragma: no cover
        return np.linalg.inv(stack)
    return _inv(stack)


def eigh_lists(stack: Array) -> tuple[list, list]:
    """``np.linalg.eigh`` of a float64 stack of symmetric matrices (lower triangle used), as
    nested lists of floats (eigenvalues ascending, eigenvectors as columns)."""
    if _eigh is None:  # pragma: no cover
        values, vectors = np.linalg.eigh(stack)
        return values.tolist(), vectors.tolist()
    values, vectors = _eigh(stack)
    value_lists = values.tolist()
    for row in value_lists:
        if not all(map(math.isfinite, row)):  # NaN-filled: let the public call raise
            values, vectors = np.linalg.eigh(stack)
            return values.tolist(), vectors.tolist()
    return value_lists, vectors.tolist()
