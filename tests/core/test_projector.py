"""Bearings, the projector Π = I − ββᵀ and its derivative (SPEC §2, §4)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.projector import (
    bearing,
    bearing_from_image_point,
    projector,
    projector_derivative_wrt_drone,
)

from .finite_difference import central_gradient

# Machine-precision identities of a 3×3 product: a few ulps of entries of size ≤ 1.
IDENTITY_ATOL = 1e-14

vectors = st.tuples(*[st.floats(-10.0, 10.0)] * 3).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1
)


@settings(deadline=None, max_examples=200, derandomize=True)
@given(vectors)
def test_projector_is_an_orthogonal_projection_onto_the_bearing_normal(v: np.ndarray) -> None:
    """Π is symmetric, idempotent, annihilates β and has trace (= rank) 2."""
    unit, distance = bearing(v)
    assert distance == np.linalg.norm(v)
    assert abs(unit @ unit - 1.0) < IDENTITY_ATOL
    proj = projector(unit)
    np.testing.assert_allclose(proj, proj.T, rtol=0, atol=0)
    np.testing.assert_allclose(proj @ proj, proj, rtol=0, atol=IDENTITY_ATOL)
    np.testing.assert_allclose(proj @ unit, np.zeros(3), rtol=0, atol=IDENTITY_ATOL)
    assert abs(np.trace(proj) - 2.0) < IDENTITY_ATOL


def _projector_of(drone: np.ndarray, target: np.ndarray) -> np.ndarray:
    return projector(bearing(target - drone)[0])


def test_projector_derivative_matches_central_differences() -> None:
    """∂Π/∂p_i (B.15) and ∂Π/∂p_r = −∂Π/∂p_i match central differences of Π(β(p_r − p_i)).

    Step 1e-6·d: |∂³Π| ≲ 6/d³ gives truncation ≲ 1e-12·6/6/d, round-off ≲ 1e-16/(1e-6·d);
    the tolerance 1e-8/d is > 50× both and ≪ the entries (~1/d).
    """
    rng = np.random.default_rng(11)
    for _ in range(50):
        target = rng.uniform(-3.0, 3.0, 3)
        drone = target + rng.normal(size=3) * rng.uniform(0.3, 8.0)
        unit, distance = bearing(target - drone)
        analytic = projector_derivative_wrt_drone(unit, distance)
        assert analytic.shape == (3, 3, 3)
        step = 1e-6 * distance
        wrt_drone = central_gradient(lambda p, t=target: _projector_of(p, t), drone, step)
        wrt_target = central_gradient(lambda t, p=drone: _projector_of(p, t), target, step)
        np.testing.assert_allclose(analytic, wrt_drone, rtol=0, atol=1e-8 / distance)
        np.testing.assert_allclose(-analytic, wrt_target, rtol=0, atol=1e-8 / distance)
        # Each slice is symmetric (Π stays symmetric) and orthogonal-to-trace (trace Π = 2).
        np.testing.assert_allclose(analytic, np.swapaxes(analytic, 1, 2), atol=IDENTITY_ATOL)
        np.testing.assert_allclose(np.trace(analytic, axis1=1, axis2=2), 0.0, atol=1e-13)


@settings(deadline=None, max_examples=200, derandomize=True)
@given(st.floats(-5.0, 5.0), st.floats(-5.0, 5.0))
def test_bearing_from_image_point_is_a_downward_unit_vector(x_bar: float, y_bar: float) -> None:
    """β from any image point [x̄, ȳ] is unit with β_z < 0 and direction [x̄, ȳ, −1]."""
    beta = bearing_from_image_point(np.array([x_bar, y_bar]))
    assert abs(beta @ beta - 1.0) < IDENTITY_ATOL
    assert beta[2] < 0.0
    np.testing.assert_allclose(beta / -beta[2], [x_bar, y_bar, -1.0], rtol=1e-13, atol=1e-13)


def test_bearing_from_noise_free_image_point_is_the_true_bearing() -> None:
    """x̄ = p_x/(−p_z), ȳ = p_y/(−p_z) of a target below the drone gives β = p_ir/‖p_ir‖."""
    rng = np.random.default_rng(5)
    tan_fov = math.tan(math.radians(50.0))
    for _ in range(200):
        depth = rng.uniform(0.5, 8.0)
        relative = np.array([*(rng.uniform(-tan_fov, tan_fov, 2) * depth), -depth])
        image_point = relative[:2] / -relative[2]
        expected, _ = bearing(relative)
        np.testing.assert_allclose(bearing_from_image_point(image_point), expected,
                                   rtol=0, atol=IDENTITY_ATOL)
