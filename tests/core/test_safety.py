"""The safety envelope's barrier rows (swarm.core.safety, issue 18): each row is the gradient
of its barrier (finite differences), u = 0 meets every row exactly when the drone is inside,
the polygon rules, and a drone pushed outward by its nominal velocity stays inside when its
velocity is the QP's answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.qp import LocalQp, QpSolver
from swarm.core.safety import (
    KeepOutCylinder,
    SafetyParams,
    convex_counter_clockwise,
    envelope_margins,
    safety_rows,
)

SQUARE = ((-5.0, -4.0), (6.0, -4.0), (6.0, 7.0), (-5.0, 7.0))
ENVELOPE = SafetyParams(floor_m=1.0, ceiling_m=5.0, keep_in=SQUARE,
                        keep_out=(KeepOutCylinder((1.0, 1.0), 1.5),
                                  KeepOutCylinder((-3.0, 5.0), 0.5)),
                        altitude_gain=0.8, fence_gain=1.3, obstacle_gain=2.0)
GAINS = [0.8, 0.8] + [1.3] * 4 + [2.0, 2.0]  # α of each row, in safety_rows' order

coordinates = st.floats(-9.0, 9.0, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(x=coordinates, y=coordinates, z=st.floats(-1.0, 7.0))
def test_each_row_is_the_gradient_of_its_barrier(x: float, y: float, z: float) -> None:
    """a = ∇h with h = −lower/α (central differences, step 1e-6 m)."""
    rows, _ = safety_rows((x, y, z), ENVELOPE)
    assert len(rows) == ENVELOPE.n_rows == len(GAINS)
    step = 1e-6
    for k, (row, gain) in enumerate(zip(rows, GAINS, strict=True)):  # lower = −αh
        for axis in range(3):
            plus, minus = [x, y, z], [x, y, z]
            plus[axis] += step
            minus[axis] -= step
            h_plus = -safety_rows(tuple(plus), ENVELOPE)[1][k] / gain
            h_minus = -safety_rows(tuple(minus), ENVELOPE)[1][k] / gain
            assert (h_plus - h_minus) / (2 * step) == pytest.approx(row[axis], abs=1e-6), (k,
                                                                                          axis)


@settings(max_examples=200, deadline=None)
@given(x=coordinates, y=coordinates, z=st.floats(-1.0, 7.0))
def test_standing_still_meets_every_row_exactly_when_inside(x: float, y: float,
                                                            z: float) -> None:
    """u = 0 meets a·u ≥ −αh iff h ≥ 0; the margins' signs agree with the barriers'."""
    _, lower = safety_rows((x, y, z), ENVELOPE)
    margins = envelope_margins((x, y, z), ENVELOPE)
    inside_every_row = all(bound <= 0.0 for bound in lower)
    assert inside_every_row == all(m >= 0.0 for m in margins.values())
    inside_square = -5.0 <= x <= 6.0 and -4.0 <= y <= 7.0
    assert (margins["fence"] >= 0) == inside_square
    assert margins["floor"] == pytest.approx(z - 1.0) and margins["ceiling"] == \
        pytest.approx(5.0 - z)
    assert margins["obstacle"] == pytest.approx(min(math.hypot(x - 1, y - 1) - 1.5,
                                                    math.hypot(x + 3, y - 5) - 0.5))


def test_the_polygon_is_kept_counter_clockwise_and_must_be_convex() -> None:
    clockwise = tuple(reversed(SQUARE))
    assert convex_counter_clockwise(clockwise) == tuple(reversed(clockwise))
    assert convex_counter_clockwise(SQUARE) == SQUARE
    for bad, words in [
            (((0, 0), (1, 0)), "at least 3 vertices"),
            (((0, 0), (4, 0), (1, 1), (0, 4)), "convex"),  # a reflex vertex
            (((0, 0), (2, 0), (4, 0), (2, 3)), "convex"),  # three on a line
            (((0, 0), (2, 2), (2, 0), (0, 2)), "convex"),  # a bow tie
            (tuple((math.cos(4 * math.pi * k / 5), math.sin(4 * math.pi * k / 5))
                   for k in range(5)), "cross itself"),  # a pentagram: every turn the same way
            (((0, 0), (1, 0), (float("nan"), 1)), "finite")]:
        with pytest.raises(ValueError, match=words):
            convex_counter_clockwise(bad)


def test_bad_envelopes_say_which_key_and_why() -> None:
    for kwargs, words in [({"floor_m": 5.0, "ceiling_m": 5.0}, "floor_m must be below"),
                          ({"floor_m": float("inf")}, "floor_m must be a finite"),
                          ({"fence_gain": 0.0}, "fence_gain must be a finite number > 0"),
                          ({"keep_out": (KeepOutCylinder((0.0, 0.0), 1.0),),
                            "obstacle_gain": -1.0}, "obstacle_gain")]:
        with pytest.raises(ValueError, match=words):
            SafetyParams(**kwargs)
    with pytest.raises(ValueError, match="radius_m must be a finite number > 0"):
        KeepOutCylinder((0.0, 0.0), 0.0)


@settings(max_examples=40, deadline=None)
@given(x=st.floats(-4.5, 5.5), y=st.floats(-3.5, 6.5), z=st.floats(1.1, 4.9),
       heading=st.floats(0.0, 2 * math.pi), climb=st.floats(-1.0, 1.0))
def test_a_drone_pushed_outward_stays_inside_when_it_flies_the_qps_answer(
        x: float, y: float, z: float, heading: float, climb: float) -> None:
    """Closed loop, ṗ = u with u the QP's nearest velocity to a nominal 2 m/s push that meets
    every envelope row (DAQP through ``QpSolver``), Euler at ΔT = 0.02 s for 20 s: every
    margin stays ≥ −(a discretization allowance), whatever the direction of the push."""
    position = np.array([x, y, z])
    if min(envelope_margins(tuple(position), ENVELOPE).values()) < 0.0:
        return  # inside the envelope only (some samples fall in an obstacle)
    push = 2.0 * np.array([math.cos(heading), math.sin(heading), climb])
    solver, dt = QpSolver(), 0.02
    worst = math.inf
    for _ in range(1000):
        rows, lower = safety_rows(tuple(position), ENVELOPE)
        qp = LocalQp(2.0 * np.eye(3), -2.0 * push, np.array(rows), np.array(lower),
                     np.full(3, -3.0), np.full(3, 3.0))
        solution = solver.solve(qp)
        assert solution.found, solution.status
        position = position + dt * solution.z[:3]
        worst = min(worst, *envelope_margins(tuple(position), ENVELOPE).values())
    # One Euler step overshoots a first-order barrier by at most (αΔT)²/2-ish of the margin
    # (h' = (1 − αΔT)h on a flat boundary: never negative); the cylinder's curvature adds
    # ΔT²‖u‖² ≈ 0.0036 m² to h = d² − r² per step at most.
    assert worst >= -0.005


# -- what mutation testing found untested (issue 46, point 2; docs/mutation.md) ------------


def test_bad_polygons_are_refused_with_their_whole_line() -> None:
    def refused(vertices: tuple[tuple[float, float], ...]) -> str:
        with pytest.raises(ValueError) as caught:
            convex_counter_clockwise(vertices)
        return str(caught.value)

    assert refused(((0, 0), (1, 0))) == "keep_in needs at least 3 vertices [x, y] (got 2)"
    assert refused(((0, 0), (1, 0), (math.nan, 1))) == (
        "keep_in vertices must be finite (got (nan, 1.0))")
    assert refused(((0, 0), (4, 0), (1, 1), (0, 4))) == (
        "keep_in must be a convex polygon (every turn the same way, no three vertices on a "
        "line) (got [(0.0, 0.0), (4.0, 0.0), (1.0, 1.0), (0.0, 4.0)])")
    pentagram = tuple((math.cos(4 * math.pi * k / 5), math.sin(4 * math.pi * k / 5))
                      for k in range(5))
    assert refused(pentagram).startswith(
        "keep_in must not cross itself (its edges wind more than once) (got [(1.0, 0.0), ")


@pytest.mark.parametrize("vertices", [
    ((0, 0), (2, 0), (3, 1), (2, 2), (1, 1.5), (0, 2)),  # a reflex vertex among six
    ((2, 5), (0, 1), (6, 4), (6, 5), (5, 5)),  # a reflex vertex among five
    ((2, 3), (4, 0), (2, 0), (0, 0)),  # clockwise, three on a line
    ((0, 0), (0.4, 0), (0.1, 0.1), (0, 0.4)),  # reflex, every turn smaller than 1
])
def test_every_turn_is_checked_however_many_vertices_and_however_small(
        vertices: tuple[tuple[float, float], ...]) -> None:
    with pytest.raises(ValueError, match="convex polygon"):
        convex_counter_clockwise(vertices)


def test_convex_polygons_of_more_vertices_and_small_turns_are_accepted() -> None:
    for n in (3, 5, 6):
        polygon = tuple((math.cos(2 * math.pi * k / n), math.sin(2 * math.pi * k / n))
                        for k in range(n))
        assert convex_counter_clockwise(polygon) == polygon
    small = ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5))  # every turn 0.25
    assert convex_counter_clockwise(small) == small


def test_a_non_finite_obstacle_centre_is_refused_with_its_key() -> None:
    with pytest.raises(ValueError,
                       match=r"^keep_out\.center_m must be a finite number \(got inf\)$"):
        KeepOutCylinder((0.0, math.inf), 1.0)
