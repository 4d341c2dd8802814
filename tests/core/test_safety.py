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
    ACTIVE_ROW_TOLERANCE,
    SLACK_USED,
    KeepOutCylinder,
    SafetyParams,
    convex_counter_clockwise,
    envelope_margins,
    fence_edges,
    safety_conflict,
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


def test_a_floor_not_below_the_ceiling_is_refused_with_its_value() -> None:
    with pytest.raises(ValueError,
                       match=r"^floor_m must be below ceiling_m = 5\.0 \(got 6\.0\)$"):
        SafetyParams(floor_m=6.0, ceiling_m=5.0)


def test_a_clockwise_keep_in_is_the_same_envelope_as_its_counter_clockwise_listing() -> None:
    """The envelope keeps the polygon counter-clockwise (as floats) however it was listed, so
    its fence rows and margins are the same (inward normals) either way round."""
    listed = ((-5, -4), (-5, 7), (6, 7), (6, -4))  # SQUARE clockwise, integers
    clockwise = SafetyParams(keep_in=listed, fence_gain=1.3)
    counter_clockwise = SafetyParams(keep_in=SQUARE, fence_gain=1.3)
    assert clockwise.keep_in == ((6.0, -4.0), (6.0, 7.0), (-5.0, 7.0), (-5.0, -4.0))
    assert all(isinstance(c, float) for vertex in clockwise.keep_in for c in vertex)
    for position in ((0.0, 0.0, 2.0), (5.5, -3.0, 2.0), (8.0, 1.0, 2.0)):
        rows, lower = safety_rows(position, clockwise)
        ccw_rows, ccw_lower = safety_rows(position, counter_clockwise)
        assert sorted(zip(rows, lower, strict=True)) == sorted(zip(ccw_rows, ccw_lower,
                                                                   strict=True))
        assert envelope_margins(position, clockwise) == envelope_margins(position,
                                                                         counter_clockwise)


def test_the_fence_edges_are_unit_inward_normals_and_the_margin_the_distance_to_the_nearest(
        ) -> None:
    """Each keep-in edge's normal is the unit vector pointing inside, at the edge's first
    vertex; the fence margin is the signed distance to the nearest edge's line."""
    assert fence_edges(SQUARE) == [((0.0, 1.0), (-5.0, -4.0)), ((-1.0, 0.0), (6.0, -4.0)),
                                   ((0.0, -1.0), (6.0, 7.0)), ((1.0, 0.0), (-5.0, 7.0))]
    triangle = ((0.0, 0.0), (4.0, 0.0), (0.0, 3.0))  # its long edge has normal (−3, −4)/5
    (normal, vertex), = fence_edges(triangle)[1:2]
    assert normal == pytest.approx((-0.6, -0.8), abs=1e-15) and vertex == (4.0, 0.0)
    envelope = SafetyParams(keep_in=SQUARE)
    for (x, y), margin in (((0.0, 0.0), 4.0),  # nearest: the bottom edge y = −4
                           ((-3.5, 2.0), 1.5),  # the left edge x = −5
                           ((5.0, 6.5), 0.5),  # the top edge y = 7
                           ((5.75, 1.0), 0.25),  # the right edge x = 6
                           ((9.0, 2.0), -3.0)):  # outside, beyond the right edge
        assert envelope_margins((x, y, 2.0), envelope)["fence"] == pytest.approx(margin,
                                                                                 abs=1e-12)


def test_the_rows_lower_bounds_are_minus_gain_times_each_barrier() -> None:
    """lower = −α h at a point whose barriers are worked out by hand: z = 2 (floor 1,
    ceiling 5), (1, 3) in the square, 2 m from the first cylinder's centre (h = 4 − 1.5²) and
    4 m from the second's (h = 16 − 0.5²)."""
    rows, lower = safety_rows((1.0, 3.0, 2.0), ENVELOPE)
    assert rows == [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0),
                    (0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 4.0, 0.0), (8.0, -4.0, 0.0)]
    hand = [2.0 - 1.0, 5.0 - 2.0, 3.0 + 4.0, 6.0 - 1.0, 7.0 - 3.0, 1.0 + 5.0,
            4.0 - 1.5 ** 2, 16.0 + 4.0 - 0.5 ** 2]
    assert lower == pytest.approx([-gain * h for gain, h in zip(GAINS, hand, strict=True)],
                                  rel=1e-15)


def _conflict_reference(rows: np.ndarray, lower: np.ndarray, n_safety: int, u: np.ndarray,
                        slacks: np.ndarray) -> bool:
    """safety_conflict in matrix form: a slack above SLACK_USED and one of the last n_safety
    rows within ACTIVE_ROW_TOLERANCE·max(1, |lower|) of its bound (or past it)."""
    if not np.any(slacks > SLACK_USED):
        return False
    first = len(lower) - n_safety
    residual = rows[first:] @ u - lower[first:]
    return bool(np.any(residual <= ACTIVE_ROW_TOLERANCE * np.maximum(1.0, np.abs(lower[first:]))))


def test_the_conflict_is_a_used_slack_while_an_envelope_row_is_active() -> None:
    """Against its matrix form on random QP answers: rows of any coefficients in the
    column-major layout, each active (a·u = lower), violated or slack by 0.01-1, the
    envelope's rows last; slacks used or not."""
    rng = np.random.default_rng(46)
    outcomes = set()
    for _ in range(400):
        n_rows = int(rng.integers(1, 7))
        n_safety = int(rng.integers(0, n_rows + 1))
        rows, u = rng.normal(size=(n_rows, 3)) * 3.0, rng.normal(size=3)
        gap = np.where(rng.random(n_rows) < 0.3, 0.0,
                       rng.choice([-1.0, 1.0], n_rows) * rng.uniform(0.01, 1.0, n_rows))
        lower = rows @ u - gap
        slacks = np.where(rng.random(3) < 0.5, rng.uniform(0.0, 1e-9, 3), rng.uniform(0, 2, 3))
        expected = _conflict_reference(rows, lower, n_safety, u, slacks)
        outcomes.add((expected, bool(np.any(slacks > SLACK_USED))))
        assert safety_conflict(rows.T.reshape(-1).tolist(), lower.tolist(), n_safety,
                               u.tolist(), slacks.tolist()) is expected
    assert outcomes == {(True, True), (False, True), (False, False)}


def test_an_envelope_row_is_active_within_its_tolerance_inclusive() -> None:
    """Active: a·u − lower ≤ ACTIVE_ROW_TOLERANCE·max(1, |lower|), at exactly that and not a
    float above; the bound scales with |lower| above 1 only. One localization row (not the
    envelope's: never counted), then one envelope row u_x ≥ lower."""
    def conflict(residual: float, lower: float) -> bool:
        return safety_conflict([0.0, 1.0, 0.0, 0.0, 0.0, 0.0], [-5.0, lower], 1,
                               [lower + residual, 0.0, 0.0], [0.5])

    tolerance = ACTIVE_ROW_TOLERANCE
    assert conflict(0.0, 0.0) and conflict(tolerance, 0.0)
    assert not conflict(math.nextafter(tolerance, 1.0), 0.0)
    assert not conflict(1.5 * tolerance, 0.5)  # |lower| < 1: the bound stays ACTIVE_ROW_TOL.
    assert conflict(100.0 * tolerance, 1000.0)  # |lower| = 1000: within 1e-6
    assert not conflict(2000.0 * tolerance, 1000.0)
    # The localization row is active and a slack is used: not the envelope's doing.
    assert not safety_conflict([1.0, 1.0, 0.0, 0.0, 0.0, 0.0], [2.0, -5.0], 1,
                               [2.0, 0.0, 0.0], [0.5])
