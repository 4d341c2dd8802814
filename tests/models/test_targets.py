"""Ground-target trajectories (SPEC §11): raised-cosine ramps, Cases 1-3 truth.

Finite-difference tolerances: a central difference with step h has truncation error
h²·max|f'''|/6 and round-off ≈ ε_mach·max|f|/h. With h = 1e-4 s, positions ≲ 20 m and
|p'''| ≲ (π/T)²/2·|v| + |a|ω³ < 0.1 m/s³ for every trajectory here, truncation ≲ 2e-10 and
round-off ≲ 2.2e-16·20/1e-4 ≈ 4e-11, so FD_TOL = 1e-8 (m/s) is ≥ 40× the worst error and still
≪ the velocities checked (0.01-1 m/s). The ramp's kinks (r'' jumps at 0 and T) only make the
h² constant a one-sided one; S = ∫r is C² there, so the bound still holds across them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.models.targets import (
    LinearTrajectory,
    OutAndBackTrajectory,
    SinusoidTrajectory,
    ramp,
    ramp_distance,
)

FD_STEP = 1e-4
FD_TOL = 1e-8
RAMP_S = 5.0

# Case 1 / Case 2 target 1, Case 2 target 2 and Case 3 (configs/case*.toml).
LINEAR = LinearTrajectory((0.1, 0.0, 0.0), (0.2, 0.3, 0.0), RAMP_S)
SINUSOID = SinusoidTrajectory((-0.1, 0.0, 0.0), (-0.2, 0.0, 0.0), (0.0, -2.2, 0.0), 0.15, RAMP_S)
OUT_AND_BACK = OutAndBackTrajectory((0.1, 0.0, 0.0), (0.2, 0.3, 0.0), 25.0, 40.0, RAMP_S)

# Dense grid plus the knots (start/end of every ramp) and points just around them.
KNOTS = (0.0, RAMP_S, 25.0, 30.0, 35.0, 40.0)
TIMES = np.unique(np.concatenate([
    np.linspace(-2.0, 50.0, 521),
    [k + d for k in KNOTS for d in (-1e-3, -2e-4, 0.0, 2e-4, 1e-3, 0.37, 2.5, 4.63)],
]))


def central_difference(f, t: float, h: float = FD_STEP) -> np.ndarray:
    return (np.asarray(f(t + h)) - np.asarray(f(t - h))) / (2.0 * h)


# -- ramp r(τ) and ramp distance S(τ) -----------------------------------------------------


def test_ramp_endpoints_and_outside_values() -> None:
    assert ramp(0.0, RAMP_S) == 0.0
    assert ramp(RAMP_S, RAMP_S) == 1.0
    assert ramp(-3.0, RAMP_S) == 0.0
    assert ramp(100.0, RAMP_S) == 1.0
    assert ramp(0.5 * RAMP_S, RAMP_S) == pytest.approx(0.5, abs=1e-15)


@pytest.mark.parametrize("ramp_s", [0.3, 1.0, 5.0, 12.0])
def test_ramp_is_continuous_with_zero_slope_at_both_ends(ramp_s: float) -> None:
    """r is C¹: values and slopes match the constant pieces at τ = 0 and τ = T.

    Near an end r ≈ (π/T)²·δ²/4, so one-sided slopes over δ = 1e-6 are ≲ 2.5e-6·(π/T)².
    """
    delta = 1e-6
    slope_bound = 3e-6 * (math.pi / ramp_s) ** 2 + 1e-9
    for end, value in ((0.0, 0.0), (ramp_s, 1.0)):
        for t in (end - delta, end + delta):
            assert abs(ramp(t, ramp_s) - value) <= slope_bound * delta + 1e-15
            assert abs((ramp(t, ramp_s) - value) / (t - end)) <= slope_bound


@pytest.mark.parametrize("ramp_s", [0.3, 1.0, 5.0, 12.0])
def test_ramp_distance_is_continuous_at_both_ends(ramp_s: float) -> None:
    assert ramp_distance(0.0, ramp_s) == 0.0
    assert ramp_distance(ramp_s, ramp_s) == pytest.approx(0.5 * ramp_s, abs=1e-15)
    delta = 1e-7
    # S(δ) ≈ (π/T)²δ³/12 near 0 and S(T ± δ) ≈ T/2 ± δ near T.
    assert abs(ramp_distance(delta, ramp_s)) < 1e-15
    assert abs(ramp_distance(-delta, ramp_s)) == 0.0
    assert ramp_distance(ramp_s - delta, ramp_s) == pytest.approx(0.5 * ramp_s - delta, abs=1e-13)
    assert ramp_distance(ramp_s + delta, ramp_s) == pytest.approx(0.5 * ramp_s + delta, abs=1e-13)
    # The ramp branch and the cruise branch give the same value at T.
    branch = 0.5 * ramp_s - ramp_s / (2.0 * math.pi) * math.sin(math.pi)
    assert branch == pytest.approx(ramp_s - 0.5 * ramp_s, abs=1e-14)


@pytest.mark.parametrize("ramp_s", [0.3, 1.0, 5.0, 12.0])
def test_ramp_distance_derivative_is_ramp(ramp_s: float) -> None:
    """S' = r by central differences, across both knots (S is C² there).

    Tolerance: 2× the truncation bound h²·max|S‴|/6 with max|S‴| = max|r″| = (π/T)²/2,
    plus 1e-10 for round-off (ε_mach·|S|/h ≲ 4e-11 here).
    """
    tol = 2.0 * FD_STEP**2 * (math.pi / ramp_s) ** 2 / 12.0 + 1e-10
    times = np.concatenate([np.linspace(-0.5 * ramp_s, 1.5 * ramp_s, 401), [0.0, ramp_s]])
    for t in times:
        fd = central_difference(lambda s: ramp_distance(s, ramp_s), float(t))
        assert fd == pytest.approx(ramp(float(t), ramp_s), abs=tol)


@settings(deadline=None, max_examples=300, derandomize=True)
@given(st.floats(0.05, 20.0), st.floats(-5.0, 30.0), st.floats(1e-3, 5.0))
def test_ramp_is_monotone_and_bounded(ramp_s: float, t: float, dt: float) -> None:
    a, b = ramp(t, ramp_s), ramp(t + dt, ramp_s)
    assert 0.0 <= a <= b <= 1.0
    # S is non-decreasing and never exceeds the distance at full speed.
    assert 0.0 <= ramp_distance(t, ramp_s) <= ramp_distance(t + dt, ramp_s)
    assert ramp_distance(t, ramp_s) <= max(t, 0.0) + 1e-12


@settings(deadline=None, max_examples=200, derandomize=True)
@given(st.floats(0.05, 20.0), st.floats(0.0, 1.0))
def test_ramp_is_point_symmetric_about_its_midpoint(ramp_s: float, fraction: float) -> None:
    """r(τ) + r(T − τ) = 1 (raised cosine)."""
    tau = fraction * ramp_s
    assert ramp(tau, ramp_s) + ramp(ramp_s - tau, ramp_s) == pytest.approx(1.0, abs=1e-14)


# -- velocity = d position / dt for every trajectory ---------------------------------------


@pytest.mark.parametrize("trajectory", [LINEAR, SINUSOID, OUT_AND_BACK],
                         ids=["linear", "sinusoid", "out_and_back"])
def test_velocity_is_the_derivative_of_position(trajectory) -> None:
    worst = 0.0
    for t in TIMES:
        fd = central_difference(trajectory.position, float(t))
        worst = max(worst, float(np.max(np.abs(fd - trajectory.velocity(float(t))))))
    assert worst < FD_TOL


@pytest.mark.parametrize("trajectory", [LINEAR, SINUSOID, OUT_AND_BACK],
                         ids=["linear", "sinusoid", "out_and_back"])
def test_positions_and_velocities_are_3_vectors_of_floats(trajectory) -> None:
    for t in (0.0, 7.3):
        for value in (trajectory.position(t), trajectory.velocity(t)):
            assert value.shape == (3,)
            assert value.dtype == np.float64
            assert np.all(np.isfinite(value))


# -- Linear (Case 1) ------------------------------------------------------------------------


def test_linear_starts_at_rest_at_start_and_reaches_its_velocity_after_the_ramp() -> None:
    start, velocity = np.array(LINEAR.start_m), np.array(LINEAR.velocity_m_s)
    for t in (-1.0, 0.0):
        np.testing.assert_array_equal(LINEAR.position(t), start)
        np.testing.assert_array_equal(LINEAR.velocity(t), np.zeros(3))
    speeds = [np.linalg.norm(LINEAR.velocity(t)) for t in np.linspace(0.0, RAMP_S, 51)]
    assert np.all(np.diff(speeds) > 0.0)
    for t in (RAMP_S, RAMP_S + 0.1, 17.0, 30.0):
        np.testing.assert_array_equal(LINEAR.velocity(t), velocity)
        # After the ramp the target lags a constant-velocity one by T/2 seconds.
        np.testing.assert_allclose(LINEAR.position(t), start + velocity * (t - 0.5 * RAMP_S),
                                   rtol=0, atol=1e-14)
    # Case 1: the final speed is ‖[0.2, 0.3, 0]‖ ≈ 0.36 m/s (the thesis' ‖u_i‖ limit).
    assert np.linalg.norm(LINEAR.velocity(30.0)) == pytest.approx(math.hypot(0.2, 0.3))


# -- Sinusoid (Case 2, target 2) -----------------------------------------------------------


def test_sinusoid_matches_the_spec_case2_formula() -> None:
    """p = [−0.1 − 0.2 S(t), −2.2 sin(0.15 t), 0] and its time derivative (SPEC §11)."""
    for t in TIMES[TIMES >= 0.0]:
        t = float(t)
        expected = np.array([-0.1 - 0.2 * ramp_distance(t, RAMP_S), -2.2 * math.sin(0.15 * t), 0.0])
        np.testing.assert_allclose(SINUSOID.position(t), expected, rtol=0, atol=1e-14)
        expected_v = np.array([-0.2 * ramp(t, RAMP_S), -2.2 * 0.15 * math.cos(0.15 * t), 0.0])
        np.testing.assert_allclose(SINUSOID.velocity(t), expected_v, rtol=0, atol=1e-14)


def test_sinusoid_starts_at_start_and_only_the_drift_is_ramped() -> None:
    np.testing.assert_array_equal(SINUSOID.position(0.0), np.array([-0.1, 0.0, 0.0]))
    # The SPEC formula has ṗ_y(0) = −2.2·0.15 = −0.33 m/s: the wave is not ramped, the drift is.
    np.testing.assert_allclose(SINUSOID.velocity(0.0), [0.0, -0.33, 0.0], rtol=0, atol=1e-15)
    # Half a period later the wave has turned round; the drift is at full speed.
    t = math.pi / 0.15
    np.testing.assert_allclose(SINUSOID.velocity(t), [-0.2, 0.33, 0.0], rtol=0, atol=1e-14)


# -- Out and back (Case 3) -----------------------------------------------------------------


def test_out_and_back_starts_at_rest_and_cruises_until_the_turn() -> None:
    start, velocity = np.array(OUT_AND_BACK.start_m), np.array(OUT_AND_BACK.velocity_m_s)
    np.testing.assert_array_equal(OUT_AND_BACK.position(0.0), start)
    np.testing.assert_array_equal(OUT_AND_BACK.velocity(0.0), np.zeros(3))
    for t in (RAMP_S, 12.0, 25.0):
        np.testing.assert_allclose(OUT_AND_BACK.velocity(t), velocity, rtol=0, atol=1e-15)


def test_out_and_back_returns_at_constant_speed_ratio() -> None:
    """Between turn + T and back − T the velocity is −k·v with k = t_turn/(t_back − T − t_turn)."""
    k = OUT_AND_BACK.return_speed_ratio
    assert k == pytest.approx(25.0 / (40.0 - 5.0 - 25.0))
    for t in (30.0, 32.0, 35.0):
        np.testing.assert_allclose(OUT_AND_BACK.velocity(t),
                                   -k * np.array(OUT_AND_BACK.velocity_m_s), rtol=0, atol=1e-14)


def test_out_and_back_ends_at_rest_exactly_at_start_and_stays() -> None:
    start = np.array(OUT_AND_BACK.start_m)
    np.testing.assert_allclose(OUT_AND_BACK.position(40.0), start, rtol=0, atol=1e-13)
    for t in (40.0, 40.02, 41.0, 45.0, 100.0, 1e4):
        np.testing.assert_allclose(OUT_AND_BACK.position(t), start, rtol=0, atol=1e-12)
        np.testing.assert_allclose(OUT_AND_BACK.velocity(t), np.zeros(3), rtol=0, atol=1e-15)
    # Just before back_s it is still (barely) moving towards the start.
    assert np.linalg.norm(OUT_AND_BACK.position(39.0) - start) > 1e-4


def test_out_and_back_goes_out_and_comes_back() -> None:
    start = np.array(OUT_AND_BACK.start_m)
    direction = np.array(OUT_AND_BACK.velocity_m_s) / np.linalg.norm(OUT_AND_BACK.velocity_m_s)
    times = np.linspace(0.0, 40.0, 2001)
    along = np.array([(OUT_AND_BACK.position(t) - start) @ direction for t in times])
    assert np.all(along >= -1e-12)
    peak = times[np.argmax(along)]
    # The target stops (velocity zero crossing) inside the turn ramp [25, 30].
    assert 25.0 < peak < 30.0
    # Motion is along the line only.
    across = [np.linalg.norm((OUT_AND_BACK.position(t) - start) - a * direction)
              for t, a in zip(times, along, strict=True)]
    assert max(across) < 1e-12


@pytest.mark.parametrize("knot", KNOTS)
def test_out_and_back_velocity_is_continuous_at_every_knot(knot: float) -> None:
    """|v(t+δ) − v(t−δ)| ≤ 2δ·max|v̇|, max|v̇| = (1 + k)·(π/2T)·|v| ≈ 0.68 m/s²."""
    delta = 1e-7
    jump = np.linalg.norm(OUT_AND_BACK.velocity(knot + delta) - OUT_AND_BACK.velocity(knot - delta))
    assert jump <= 2 * delta * 0.7 + 1e-15


@pytest.mark.parametrize("turn_s, back_s, ramp_s", [
    (25.0, 35.0, 5.0),  # back_s = turn_s + 2·ramp_s: the return ramps would touch
    (25.0, 30.0, 5.0),
    (25.0, 20.0, 5.0),  # back before the turn
    (25.0, math.nan, 5.0),
    (math.nan, 40.0, 5.0),
])
def test_out_and_back_rejects_an_impossible_schedule(turn_s: float, back_s: float,
                                                    ramp_s: float) -> None:
    with pytest.raises(ValueError, match="back_s"):
        OutAndBackTrajectory((0.0, 0.0, 0.0), (0.2, 0.3, 0.0), turn_s, back_s, ramp_s)


def test_out_and_back_rejects_a_turn_before_the_start() -> None:
    with pytest.raises(ValueError):
        OutAndBackTrajectory((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), turn_s=-5.0, back_s=10.0,
                             ramp_s=5.0)
