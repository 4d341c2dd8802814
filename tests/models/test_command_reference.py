"""The command reference (swarm.models.command_reference): the single integrator along the
commands."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from swarm.models.command_reference import CommandReference

finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)


@given(st.lists(st.tuples(vec3, st.floats(0.005, 0.1)), min_size=2, max_size=40))
def test_the_reference_integrates_the_commands_exactly(steps) -> None:
    """A vehicle that flies exactly its command stays on the reference: the reference is
    Σ Δt_k·u_(k−1) from where it started, the velocity error is 0, nothing is reset; the
    acceleration feed-forward is the command's difference quotient."""
    reference = CommandReference(reset_distance_m=1.0)
    position = (1.0, -2.0, 3.0)
    previous = None
    for command, elapsed in steps:
        if previous is not None:
            position = tuple(p + elapsed * u for p, u in zip(position, previous, strict=True))
        sp = reference.setpoint(position, previous, command, elapsed)
        assert sp.position_w == pytest.approx(position, abs=1e-9)
        assert sp.position_error_m == pytest.approx(0.0, abs=1e-9) and not sp.reset
        assert sp.velocity_w == command
        if previous is None:
            assert sp.velocity_error_m_s is None and sp.acceleration_w == (0.0, 0.0, 0.0)
        else:
            assert sp.velocity_error_m_s == 0.0
            assert sp.acceleration_w == pytest.approx(
                [(u - v) / elapsed for u, v in zip(command, previous, strict=True)])
        previous = command
    assert reference.resets == 0


def test_a_vehicle_that_falls_behind_pulls_the_reference_back_only_past_the_reset_distance(
) -> None:
    reference = CommandReference(reset_distance_m=0.5)
    reference.setpoint((0.0, 0.0, 3.0), None, (1.0, 0.0, 0.0), 0.02)
    # The vehicle did not move for 0.4 s: the reference is 0.4 m ahead, kept.
    sp = reference.setpoint((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.4)
    assert sp.position_w == pytest.approx((0.4, 0.0, 3.0)) and not sp.reset
    assert sp.position_error_m == pytest.approx(0.4) and sp.velocity_error_m_s == 1.0
    # Another 0.2 s standing still: 0.6 m > 0.5 m, so the reference is put on the vehicle.
    sp = reference.setpoint((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.2)
    assert sp.reset and sp.position_w == (0.0, 0.0, 3.0) and reference.resets == 1
    assert sp.position_error_m == pytest.approx(0.6)


@pytest.mark.parametrize("bad", [0.0, -0.02, math.nan, math.inf])
def test_bad_times_and_distances_are_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="elapsed_s"):
        CommandReference(1.0).setpoint((0.0, 0.0, 0.0), None, (0.0, 0.0, 0.0), bad)
    with pytest.raises(ValueError, match="reset_distance_m"):
        CommandReference(bad if bad <= 0 or not math.isfinite(bad) else -1.0)


def test_a_restarted_reference_starts_on_the_vehicle_again() -> None:
    reference = CommandReference(reset_distance_m=0.5)
    reference.setpoint((0.0, 0.0, 3.0), None, (1.0, 0.0, 0.0), 0.02)
    reference.restart()
    sp = reference.setpoint((5.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.3)
    assert sp.position_w == (5.0, 0.0, 3.0) and not sp.reset and reference.resets == 0
    assert sp.velocity_error_m_s is None and sp.acceleration_w == (0.0, 0.0, 0.0)


# -- what mutation testing found untested (docs/mutation.md) --------------------------------


def test_no_reference_before_the_first_setpoint_and_no_velocity_error_at_it() -> None:
    reference = CommandReference(reset_distance_m=0.5)
    assert reference.position_w is None
    sp = reference.setpoint((0.0, 0.0, 3.0), (0.2, 0.0, 0.0), (1.0, 0.0, 0.0), 0.02)
    assert sp.velocity_error_m_s is None  # no earlier command to compare with


def test_a_vehicle_exactly_at_the_reset_distance_is_kept_and_each_reset_counts() -> None:
    reference = CommandReference(reset_distance_m=0.5)
    reference.setpoint((0.0, 0.0, 3.0), None, (1.0, 0.0, 0.0), 0.02)
    sp = reference.setpoint((0.0, 0.0, 3.0), None, (0.0, 0.0, 0.0), 0.5)  # r 0.5 m ahead
    assert sp.position_error_m == 0.5 and not sp.reset and reference.resets == 0
    reference.setpoint((0.0, 0.0, 3.0), None, (2.0, 0.0, 0.0), 0.25)  # r stays 0.5 m ahead
    sp = reference.setpoint((0.0, 0.0, 3.0), None, (2.0, 0.0, 0.0), 0.25)  # r 1 m ahead
    assert sp.reset and reference.resets == 1
    sp = reference.setpoint((0.0, 0.0, 3.0), None, (0.0, 0.0, 0.0), 0.5)  # 1 m again
    assert sp.reset and reference.resets == 2


def test_the_tracking_error_is_the_distance_in_all_three_axes() -> None:
    reference = CommandReference(reset_distance_m=1.0)
    reference.setpoint((0.0, 0.0, 3.0), None, (0.0, 0.0, 0.0), 0.02)
    sp = reference.setpoint((0.0, 0.3, 3.4), (0.0, 0.6, 0.8), (0.0, 0.0, 0.0), 0.02)
    assert sp.position_error_m == pytest.approx(0.5) and not sp.reset
    assert sp.velocity_error_m_s == pytest.approx(1.0)
