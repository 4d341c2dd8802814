"""Single-integrator drones: box-bounded velocity, Euler step, seeded start positions (SPEC §1)."""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.models.kinematics import (
    ARDUCOPTER_SITL_RESPONSE,
    VelocityResponse,
    clamp_velocity,
    sample_initial_positions,
    step_drone,
    step_vehicle,
)

U_MAX = 3.0
CENTER = np.array([0.0, 0.0, 3.5])  # SPEC §11 start box
SIZE = np.array([4.0, 4.0, 2.0])

components = st.floats(-1e6, 1e6, allow_nan=False)


@settings(deadline=None, max_examples=300, derandomize=True)
@given(st.tuples(components, components, components), st.floats(0.01, 10.0))
def test_clamp_is_a_per_component_box(velocity: tuple[float, float, float],
                                      u_max: float) -> None:
    command = np.array(velocity)
    clamped = clamp_velocity(command, u_max)
    assert clamped.shape == (3,)
    for k in range(3):
        assert abs(clamped[k]) <= u_max
        if abs(command[k]) <= u_max:
            assert clamped[k] == command[k]  # inside the box: untouched
        else:
            assert clamped[k] == math.copysign(u_max, command[k])


def test_clamp_examples() -> None:
    np.testing.assert_array_equal(clamp_velocity(np.array([5.0, -7.0, 1.0]), U_MAX),
                                  [3.0, -3.0, 1.0])
    # A box, not a ball: the direction is not preserved and the norm may reach √3·u_max.
    clamped = clamp_velocity(np.array([10.0, 10.0, -10.0]), U_MAX)
    np.testing.assert_array_equal(clamped, [3.0, 3.0, -3.0])
    assert np.linalg.norm(clamped) == pytest.approx(math.sqrt(3) * U_MAX)
    np.testing.assert_array_equal(clamp_velocity(np.array([3.0, -3.0, 0.0]), U_MAX),
                                  [3.0, -3.0, 0.0])


@pytest.mark.parametrize("bad", [
    [math.nan, 0.0, 0.0],
    [0.1, math.nan, 0.2],
    [math.nan] * 3,
    [math.inf, 0.0, 0.0],
    [0.0, -math.inf, 1.0],
])
def test_non_finite_command_is_zero(bad: list[float]) -> None:
    np.testing.assert_array_equal(clamp_velocity(np.array(bad), U_MAX), np.zeros(3))


def test_clamp_does_not_modify_its_input() -> None:
    command = np.array([5.0, -1.0, math.nan])
    before = command.copy()
    clamp_velocity(command, U_MAX)
    np.testing.assert_array_equal(command, before)
    command = np.array([5.0, -1.0, 0.0])
    clamp_velocity(command, U_MAX)
    np.testing.assert_array_equal(command, [5.0, -1.0, 0.0])


def test_step_drone_is_forward_euler_with_the_clamped_command() -> None:
    p = np.array([1.0, -2.0, 3.5])
    dt = 0.02
    np.testing.assert_array_equal(step_drone(p, np.array([0.5, -1.0, 0.25]), U_MAX, dt),
                                  p + dt * np.array([0.5, -1.0, 0.25]))
    np.testing.assert_array_equal(step_drone(p, np.array([9.0, -9.0, 0.0]), U_MAX, dt),
                                  p + dt * np.array([3.0, -3.0, 0.0]))
    np.testing.assert_array_equal(step_drone(p, np.array([math.nan, 1.0, 1.0]), U_MAX, dt), p)
    np.testing.assert_array_equal(p, [1.0, -2.0, 3.5])  # input untouched


def test_constant_command_integrates_linearly() -> None:
    p = np.array([0.0, 0.0, 3.0])
    u = np.array([0.2, 0.3, -0.1])
    for _ in range(50):
        p = step_drone(p, u, U_MAX, 0.02)
    np.testing.assert_allclose(p, [0.2, 0.3, 2.9], rtol=0, atol=1e-13)


# -- initial positions ---------------------------------------------------------------------


def _check_layout(positions: np.ndarray, n: int, center: np.ndarray, size: np.ndarray,
                  separation: float) -> None:
    assert positions.shape == (n, 3)
    assert np.all(positions >= center - size / 2)
    assert np.all(positions <= center + size / 2)
    for a, b in combinations(range(n), 2):
        assert np.linalg.norm(positions[a] - positions[b]) >= separation


@pytest.mark.parametrize("seed", range(10))
def test_initial_positions_respect_box_and_separation(seed: int) -> None:
    positions = sample_initial_positions(6, CENTER, SIZE, 1.0, np.random.default_rng(seed))
    _check_layout(positions, 6, CENTER, SIZE, 1.0)


@pytest.mark.parametrize("n, separation", [(2, 3.0), (12, 1.0), (20, 0.8)])
def test_initial_positions_in_denser_boxes(n: int, separation: float) -> None:
    positions = sample_initial_positions(n, CENTER, SIZE, separation, np.random.default_rng(1))
    _check_layout(positions, n, CENTER, SIZE, separation)


def test_flat_box_gives_coplanar_positions() -> None:
    size = np.array([6.0, 6.0, 0.0])
    positions = sample_initial_positions(6, CENTER, size, 1.0, np.random.default_rng(4))
    _check_layout(positions, 6, CENTER, size, 1.0)
    np.testing.assert_array_equal(positions[:, 2], np.full(6, 3.5))


def test_initial_positions_are_deterministic_for_a_seed() -> None:
    a = sample_initial_positions(6, CENTER, SIZE, 1.0, np.random.default_rng(123))
    b = sample_initial_positions(6, CENTER, SIZE, 1.0, np.random.default_rng(123))
    c = sample_initial_positions(6, CENTER, SIZE, 1.0, np.random.default_rng(124))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_initial_positions_accept_lists() -> None:
    a = sample_initial_positions(3, [0.0, 0.0, 3.5], [4.0, 4.0, 2.0], 1.0,
                                 np.random.default_rng(9))
    b = sample_initial_positions(3, CENTER, SIZE, 1.0, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("size, n, separation", [
    ([0.0, 0.0, 0.0], 2, 1.0),  # a point cannot hold two drones
    ([1.0, 0.0, 0.0], 2, 1.0),  # segment [−0.5, 0.5): every distance < 1
    ([0.5, 0.5, 0.5], 6, 1.0),  # cube diagonal ≈ 0.87 < 1
])
def test_impossible_layout_raises_a_clear_error(size: list[float], n: int,
                                                 separation: float) -> None:
    with pytest.raises(ValueError, match=r"could not place \d+ drones .* enlarge "
                                         r"initial_box_size_m") as info:
        sample_initial_positions(n, CENTER, np.array(size), separation,
                                 np.random.default_rng(0), max_tries=2000)
    assert "\n" not in str(info.value)


def test_impossible_layout_with_default_tries_terminates() -> None:
    with pytest.raises(ValueError, match="after 10000 tries"):
        sample_initial_positions(2, CENTER, np.zeros(3), 1.0, np.random.default_rng(0))


def test_zero_drones_gives_an_empty_layout() -> None:
    positions = sample_initial_positions(0, CENTER, SIZE, 1.0, np.random.default_rng(0),
                                         max_tries=10)
    assert positions.shape == (0, 3)


# -- velocity response (swarm.models.kinematics.VelocityResponse) ------------------------------

vectors = st.lists(st.floats(-5, 5), min_size=3, max_size=3).map(np.array)


@given(vectors, vectors)
def test_the_ideal_response_is_the_command_itself_bit_for_bit(velocity: np.ndarray,
                                                             command: np.ndarray) -> None:
    position = np.array([1.0, -2.0, 3.0])
    p, v = step_vehicle(position, velocity, command, U_MAX, 0.02, VelocityResponse())
    assert np.array_equal(v, clamp_velocity(command, U_MAX))
    assert np.array_equal(p, step_drone(position, command, U_MAX, 0.02))


@given(vectors, vectors, st.floats(0.05, 2.0), st.floats(0.001, 0.1))
def test_a_lag_is_the_exact_first_order_step(velocity: np.ndarray, command: np.ndarray,
                                             tau: float, dt: float) -> None:
    """Without an acceleration limit: v_(k+1) = u + (v_k − u)·e^(−ΔT/τ), the exact solution of
    τ·v̇ = u − v over ΔT."""
    v = VelocityResponse(time_constant_s=tau).step(velocity, command, dt)
    np.testing.assert_allclose(v, command + (velocity - command) * math.exp(-dt / tau),
                               rtol=0, atol=1e-12)


@given(vectors, vectors, st.floats(0.0, 1.0), st.floats(0.1, 5.0), st.floats(0.001, 0.1))
def test_the_acceleration_never_exceeds_the_limit(velocity: np.ndarray, command: np.ndarray,
                                                  tau: float, limit: float, dt: float) -> None:
    response = VelocityResponse(time_constant_s=tau, accel_limit_m_s2=limit)
    v = response.step(velocity, command, dt)
    # (v − v_k is read back through a rounded sum: allow the rounding of numbers of that size)
    rounding = 8 * np.finfo(float).eps * (np.linalg.norm(velocity) + np.linalg.norm(command))
    assert np.linalg.norm(v - velocity) <= limit * dt * (1 + 1e-12) + rounding
    # and it moves toward the command, never past it
    assert np.linalg.norm(command - v) <= np.linalg.norm(command - velocity) + rounding


def test_a_step_command_is_followed_within_the_time_constant_and_the_limit() -> None:
    response = ARDUCOPTER_SITL_RESPONSE
    v, p = np.zeros(3), np.zeros(3)
    speeds = []
    for _ in range(250):  # 5 s at 50 Hz of 1 m/s east
        p, v = step_vehicle(p, v, np.array([1.0, 0.0, 0.0]), U_MAX, 0.02, response)
        speeds.append(v[0])
    rate_limited = 1.0 / response.accel_limit_m_s2  # the time a pure rate limit would take
    reached = 0.02 * (1 + next(k for k, s in enumerate(speeds) if s >= 1.0 - math.exp(-1)))
    assert rate_limited * (1 - math.exp(-1)) <= reached <= rate_limited + response.time_constant_s
    assert speeds[-1] == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("field, value", [("time_constant_s", -0.1),
                                          ("accel_limit_m_s2", math.inf),
                                          ("time_constant_s", math.nan)])
def test_response_parameters_are_checked(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        VelocityResponse(**{field: value})
