"""Bearings and the orthogonal projector Π = I − ββᵀ with its derivatives (SPEC §2, §4).

Small 3-vectors only: hand-written outer products instead of ``np.kron`` / ``np.cross``,
which cost far more than the arithmetic on arrays this size.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]

_EYE3 = np.eye(3)


def bearing(relative_position: Vec3) -> tuple[Vec3, float]:
    """Unit bearing β = p_ir/‖p_ir‖ and distance d = ‖p_ir‖ (SPEC §2, thesis 1.6)."""
    distance = float(np.sqrt(relative_position @ relative_position))
    return relative_position / distance, distance


def bearing_from_image_point(image_point: NDArray[np.float64]) -> Vec3:
    """Bearing in the world frame from a (noisy) image-plane point [x̄, ȳ] (SPEC §2, 1.7-1.10).

    The camera is gimballed with its optical axis along −z of W, so the point in drone
    coordinates is [x̄, ȳ, −1] and needs no rotation.
    """
    ray = np.array([image_point[0], image_point[1], -1.0])
    bearing: Vec3 = ray / np.sqrt(ray @ ray)
    return bearing


def projector(unit_bearing: Vec3) -> Mat3:
    """Π_β = I − ββᵀ, the projector onto the plane orthogonal to β (SPEC §4, thesis 2.3)."""
    return _EYE3 - np.outer(unit_bearing, unit_bearing)


def projector_derivative_wrt_drone(unit_bearing: Vec3, distance: float) -> NDArray[np.float64]:
    """∂Π/∂p_i,k for k = x, y, z as a (3, 3, 3) array indexed [k] (SPEC §4, thesis B.15).

    ∂Π/∂p_i,k = (1/d)[(e_k − β_k β)βᵀ + β(e_k − β_k β)ᵀ]; the derivative with respect to the
    target position is the negative of this.
    """
    b = unit_bearing
    # Rows of (I − ββᵀ) are e_k − β_k β.
    tangents = _EYE3 - np.outer(b, b)
    first = tangents[:, :, None] * b[None, None, :]  # [k, a, c] = t_k[a] β[c]
    return (first + np.swapaxes(first, 1, 2)) / distance
