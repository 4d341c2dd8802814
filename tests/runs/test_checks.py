"""The judge on its own: every invariant check of ``swarm.runs.checks`` on records built by
hand (issue 46, point 1; issue 41, points 2-3).

Each check is held to the places where a loop bound, an index or a comparison is easy to get
wrong: a violation at the first and at the last step, by the first and by the last drone (and
pair), exactly at the tolerance (holds) and one float past it (does not), NaN (missing)
samples, one drone and many. The report, its JSON and the launcher's summary must say what
the check says. Every record here is a handful of steps of plain arrays: seconds in all.
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from rich.console import Console

from swarm.errors import EXIT_FAILED, EXIT_INCOMPLETE, EXIT_OK
from swarm.observe.report import build_report, report_to_json, verdict_line
from swarm.runs import checks
from swarm.runs.checks import (
    Violation,
    check_invariants,
    closest_pair_per_step,
    min_pairwise_distance,
    start_index,
)
from swarm.runs.record import RunRecord
from swarm.scenario.config import ScenarioConfig, load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
DURATION_S = 2.0  # 100 steps of 0.02 s; control.start_s = 1 s is step 50
SPACING_M = 2.0  # drones on a line along x, far from each other and from every boundary


def scenario(case: str = "case1") -> ScenarioConfig:
    return load_config(CONFIGS / f"{case}.toml").with_duration(DURATION_S)


def clean_record(n_drones: int = 4, *, case: str = "case1", steps: int | None = None
                 ) -> RunRecord:
    """A run that holds every invariant with room to spare: drones hovering SPACING_M apart
    at 3 m, every λ̄ copy at 1 (ε = 0.05), every command 0.1 m/s along x, estimates exact."""
    config = scenario(case)
    k = config.n_steps if steps is None else steps
    m = len(config.targets)
    n_state = config.state_dimension
    positions = np.zeros((k, n_drones, 3))
    positions[:, :, 0] = SPACING_M * np.arange(n_drones)
    positions[:, :, 2] = 3.0
    targets = np.zeros((k, m, 3))
    estimates = np.zeros((k, n_drones, m, n_state))
    velocities = np.zeros((k, n_drones, 3))
    velocities[..., 0] = 0.1
    per_target = np.ones((k, n_drones, m))
    return RunRecord(
        config=config, seed=0, times_s=np.arange(k) * config.scenario.dt_s,
        drone_positions_m=positions, velocities_m_s=velocities, target_positions_m=targets,
        target_velocities_m_s=np.zeros((k, m, 3)), estimates=estimates,
        lambda_bar=per_target.copy(), psi0=per_target - 0.05, psi1=per_target.copy(),
        weights=per_target.copy(), slacks=np.zeros((k, n_drones, m)),
        weight_slacks=np.zeros((k, n_drones, m)), detected=np.ones((k, n_drones, m), bool),
        true_lambda_min=np.ones((k, m)), measured_lambda_min=np.ones((k, m)),
        bearing_errors=np.full((k, n_drones), np.nan),
        qp_fallback=np.zeros((k, n_drones), bool), step_us=np.full((k, n_drones), 50.0),
        wall_time_s=1.0, safety_conflict=np.zeros((k, n_drones), bool))


def changed(record: RunRecord, **arrays_by_name: np.ndarray) -> RunRecord:
    return dataclasses.replace(record, **arrays_by_name)


def collision_floor(config: ScenarioConfig) -> float:
    return config.control.collision_distance_m - config.checks.collision_tolerance_m


def lambda_floor(config: ScenarioConfig) -> float:
    return config.gramian.epsilon - config.checks.lambda_tolerance


def past(limit: float, *, below: bool) -> float:
    """The next float beyond ``limit``."""
    return float(np.nextafter(limit, -np.inf if below else np.inf))


def only(violations: list[Violation], invariant: str) -> Violation:
    [violation] = [v for v in violations if v.invariant == invariant]
    return violation


FIRST_LAST = [0, -1]


def test_a_clean_record_holds_every_invariant_and_is_complete() -> None:
    record = clean_record()
    assert check_invariants(record) == []
    report = build_report(record)
    assert report.ok and report.verdict == "ok" and report.exit_code == EXIT_OK
    assert verdict_line(report).startswith("verdict: OK")


# -- collision -----------------------------------------------------------------------------


def put_pair(record: RunRecord, step: int, pair: tuple[int, int], distance: float
             ) -> RunRecord:
    """Drone pair[1] moved to ``distance`` along +y from drone pair[0] at ``step``."""
    positions = record.drone_positions_m.copy()
    positions[step, pair[1]] = positions[step, pair[0]] + [0.0, distance, 0.0]
    return changed(record, drone_positions_m=positions)


@pytest.mark.parametrize("step", FIRST_LAST)
@pytest.mark.parametrize("which", ["first pair", "last pair"])
def test_collision_at_the_first_and_last_step_by_the_first_and_last_pair(
        step: int, which: str) -> None:
    base = clean_record(5)
    pair = (0, 1) if which == "first pair" else (3, 4)
    floor = collision_floor(base.config)
    at = put_pair(base, step, pair, floor)
    assert min_pairwise_distance(at) == floor  # exactly at Δ − tol: held
    assert [v for v in check_invariants(at) if v.invariant == "collision"] == []
    beyond = put_pair(base, step, pair, past(floor, below=True))
    violation = only(check_invariants(beyond), "collision")
    t = float(base.times_s[step])
    assert violation.subject == violation.first_subject == f"drones {pair[0]} and {pair[1]}"
    assert violation.worst_time_s == violation.first_time_s == t
    assert violation.limit == floor and 0 < violation.excess < 1e-12
    assert violation.time_beyond_s == pytest.approx(base.config.scenario.dt_s)
    assert f"drones {pair[0]} and {pair[1]} at t = {t:.2f} s" in violation.detail


def test_collision_names_the_first_crossing_apart_from_the_worst() -> None:
    record = clean_record(4)
    floor = collision_floor(record.config)
    record = put_pair(record, 10, (0, 1), floor - 0.01)  # first, shallow
    record = put_pair(record, 11, (0, 1), floor - 0.01)
    record = put_pair(record, 70, (2, 3), 0.2)  # later, deepest
    v = only(check_invariants(record), "collision")
    assert (v.subject, v.worst_time_s) == ("drones 2 and 3", float(record.times_s[70]))
    assert v.worst_value == pytest.approx(0.2)
    assert (v.first_subject, v.first_time_s) == ("drones 0 and 1", float(record.times_s[10]))
    assert v.excess == pytest.approx(floor - 0.2)
    assert v.time_beyond_s == pytest.approx(3 * 0.02)
    assert "first below at t = 0.20 s (drones 0 and 1), below for 0.06 s" in v.detail


def test_collision_with_a_missing_position_is_not_a_collision_and_none_is_not_checked() -> None:
    record = put_pair(clean_record(3), 30, (1, 2), 0.1)
    positions = record.drone_positions_m.copy()
    positions[30, 2] = np.nan  # the colliding sample never arrived
    assert check_invariants(changed(record, drone_positions_m=positions)) == []
    positions[:, 1:] = np.nan  # never two positions at once
    violation = only(check_invariants(changed(record, drone_positions_m=positions)),
                     "collision")
    assert "not checked" in violation.detail and violation.worst_time_s is None


def test_one_drone_has_no_pair_to_check() -> None:
    violation = only(check_invariants(clean_record(1)), "collision")
    assert "not checked" in violation.detail


def test_many_drones_the_last_pair_is_seen() -> None:
    record = put_pair(clean_record(24), -1, (22, 23), 0.3)
    assert only(check_invariants(record), "collision").subject == "drones 22 and 23"


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(0, 6), st.just(3)),
              elements=st.one_of(st.floats(-5, 5), st.just(math.nan))),
       st.integers(1, 40))
def test_closest_pair_per_step_is_the_brute_force_minimum(positions: np.ndarray,
                                                          chunk_values: int) -> None:
    """Every step's closest present pair, whatever the chunk the steps are taken in."""
    original = checks._PAIR_CHUNK_VALUES
    checks._PAIR_CHUNK_VALUES = chunk_values
    try:
        distance, pair = closest_pair_per_step(positions)
    finally:
        checks._PAIR_CHUNK_VALUES = original
    for k in range(positions.shape[0]):
        candidates = [(float(np.linalg.norm(positions[k, i] - positions[k, j])), i, j)
                      for i, j in itertools.combinations(range(positions.shape[1]), 2)]
        candidates = [c for c in candidates if not math.isnan(c[0])]
        if not candidates:
            assert math.isnan(distance[k]) and pair[k].tolist() == [-1, -1]
            continue
        best = min(c[0] for c in candidates)
        # One norm and a row of norms round differently (BLAS dot against a reduction):
        # equal to a few ulps, not bit for bit.
        assert distance[k] == pytest.approx(best, rel=1e-14, abs=0.0)
        i, j = pair[k]
        pair_distance = float(np.linalg.norm(positions[k, i] - positions[k, j]))
        assert i < j and pair_distance == pytest.approx(best, rel=1e-14, abs=0.0)


# -- λ̄ -------------------------------------------------------------------------------------


def put_lambda(record: RunRecord, step: int, drone: int, value: float) -> RunRecord:
    lam = record.lambda_bar.copy()
    lam[step, drone, 0] = value
    return changed(record, lambda_bar=lam)


@pytest.mark.parametrize("when", ["first checked step", "last step"])
@pytest.mark.parametrize("drone", FIRST_LAST)
def test_lambda_bar_at_the_first_and_last_step_by_the_first_and_last_drone(
        when: str, drone: int) -> None:
    base = clean_record(4)
    step = start_index(base) if when == "first checked step" else base.n_steps - 1
    floor = lambda_floor(base.config)
    assert check_invariants(put_lambda(base, step, drone, floor)) == []
    violation = only(check_invariants(put_lambda(base, step, drone, past(floor, below=True))),
                     "lambda_bar")
    drone_id = drone % 4
    assert violation.subject == violation.first_subject == f"target 0, drone {drone_id}"
    assert violation.worst_time_s == violation.first_time_s == float(base.times_s[step])
    assert violation.limit == floor and violation.excess > 0
    assert f"target 0: drone {drone_id} has λ̄" in violation.detail


def test_lambda_bar_before_start_is_not_checked_and_missing_samples_are_skipped() -> None:
    base = clean_record(3)
    k0 = start_index(base)
    assert check_invariants(put_lambda(base, k0 - 1, 0, -1.0)) == []  # warm-up
    missing = put_lambda(base, k0 + 3, 1, math.nan)
    velocities = missing.velocities_m_s.copy()
    velocities[k0 + 3, 1] = np.nan  # the whole sample never arrived
    assert check_invariants(changed(missing, velocities_m_s=velocities)) == []
    lam = base.lambda_bar.copy()
    lam[k0:] = np.nan
    violation = only(check_invariants(changed(base, lambda_bar=lam)), "lambda_bar")
    assert "not checked" in violation.detail


def test_lambda_bar_first_crossing_and_time_below() -> None:
    record = clean_record(3)
    k0 = start_index(record)
    floor = lambda_floor(record.config)
    record = put_lambda(record, k0 + 2, 2, floor - 0.001)
    record = put_lambda(record, k0 + 2, 0, floor - 0.001)  # same step: the lower id first
    record = put_lambda(record, k0 + 9, 1, floor - 0.02)
    v = only(check_invariants(record), "lambda_bar")
    assert (v.subject, v.first_subject) == ("target 0, drone 1", "target 0, drone 0")
    assert v.time_beyond_s == pytest.approx(2 * 0.02)
    assert v.excess == pytest.approx(0.02)


# -- envelope ------------------------------------------------------------------------------


ENVELOPE_TOLERANCE_M = 2.0**-7  # exact in binary: ceiling + it is exact, so is its margin


@pytest.mark.parametrize("step", FIRST_LAST)
@pytest.mark.parametrize("drone", FIRST_LAST)
def test_envelope_ceiling_at_the_first_and_last_step_by_the_first_and_last_drone(
        step: int, drone: int) -> None:
    base = clean_record(3, case="case2_envelope")
    config = dataclasses.replace(base.config, checks=dataclasses.replace(
        base.config.checks, envelope_tolerance_m=ENVELOPE_TOLERANCE_M))
    base = dataclasses.replace(base, config=config)
    ceiling = config.safety.params.ceiling_m
    assert check_invariants(base) == []
    positions = base.drone_positions_m.copy()
    positions[step, drone, 2] = ceiling + ENVELOPE_TOLERANCE_M  # exactly at the tolerance
    at = changed(base, drone_positions_m=positions)
    assert checks.envelope_margin_series(at)["ceiling"][step, drone] == -ENVELOPE_TOLERANCE_M
    assert check_invariants(at) == []
    positions[step, drone, 2] = past(ceiling + ENVELOPE_TOLERANCE_M, below=False)
    v = only(check_invariants(changed(base, drone_positions_m=positions)), "envelope")
    assert v.subject == v.first_subject == f"ceiling, drone {drone % 3}"
    assert v.worst_time_s == v.first_time_s == float(base.times_s[step])
    assert 0 < v.excess < 1e-12
    assert f"drone {drone % 3} went" in v.detail and "beyond the ceiling" in v.detail


# -- velocity bound ------------------------------------------------------------------------


@pytest.mark.parametrize("step", FIRST_LAST)
@pytest.mark.parametrize(("drone", "axis"), [(0, 0), (-1, 2)])
def test_velocity_bound_at_the_first_and_last_step_by_the_first_and_last_drone(
        step: int, drone: int, axis: int) -> None:
    base = clean_record(3)
    u_max = base.config.control.u_max_m_s
    velocities = base.velocities_m_s.copy()
    velocities[step, drone, axis] = -u_max  # at the bound, either sign: held
    assert check_invariants(changed(base, velocities_m_s=velocities)) == []
    velocities[step, drone, axis] = -(u_max + 1e-6)
    v = only(check_invariants(changed(base, velocities_m_s=velocities)), "velocity_bound")
    assert v.subject == f"drone {drone % 3}, u_{'xyz'[axis]}"
    assert v.worst_time_s == v.first_time_s == float(base.times_s[step])
    assert v.excess == pytest.approx(1e-6)


def test_velocity_bound_without_any_command_is_not_checked() -> None:
    base = clean_record(2)
    violation = only(check_invariants(changed(
        base, velocities_m_s=np.full_like(base.velocities_m_s, np.nan))), "velocity_bound")
    assert "not checked" in violation.detail


# -- finiteness ----------------------------------------------------------------------------


def test_a_nan_inside_a_received_sample_is_a_finite_violation_naming_it() -> None:
    base = clean_record(3)
    velocities = base.velocities_m_s.copy()
    velocities[-1, 2, 1] = np.nan  # λ̄ of that sample is there: it was received
    v = only(check_invariants(changed(base, velocities_m_s=velocities)), "finite")
    assert v.subject == "drone 2's command" and v.first_time_s == float(base.times_s[-1])
    assert "1 received samples non-finite" in v.detail


def test_a_sample_that_never_arrived_is_missing_not_non_finite() -> None:
    base = clean_record(3)
    velocities, lam = base.velocities_m_s.copy(), base.lambda_bar.copy()
    velocities[0, 0] = np.nan
    lam[0, 0] = np.nan
    assert check_invariants(changed(base, velocities_m_s=velocities, lambda_bar=lam)) == []


def test_an_infinite_position_is_a_finite_violation() -> None:
    base = clean_record(3)
    positions = base.drone_positions_m.copy()
    positions[0, 0, 2] = np.inf
    v = only(check_invariants(changed(base, drone_positions_m=positions)), "finite")
    assert v.subject == "drone 0's position (inf)" and "a position is inf" in v.detail


# -- a run cut short -----------------------------------------------------------------------


def test_a_cut_short_record_is_incomplete_not_ok() -> None:
    record = clean_record(3, steps=60)
    assert check_invariants(record) == []
    report = build_report(record)
    assert not report.ok and report.verdict == "incomplete"
    assert report.exit_code == EXIT_INCOMPLETE != EXIT_FAILED
    assert verdict_line(report).startswith("verdict: INCOMPLETE: 60 of 100 steps")
    document = json.loads(json.dumps(report_to_json(report), allow_nan=False))
    assert (document["verdict"], document["complete"], document["steps"],
            document["planned_steps"]) == ("incomplete", False, 60, 100)


def test_a_cut_short_record_with_a_violation_is_failed_and_says_incomplete() -> None:
    record = put_pair(clean_record(3, steps=60), 5, (0, 1), 0.1)
    report = build_report(record)
    assert report.verdict == "violated" and report.exit_code == EXIT_FAILED
    line = verdict_line(report)
    assert line.startswith("verdict: FAILED (collision")
    assert line.endswith("in an INCOMPLETE run: 60 of 100 steps")


# -- the report, its JSON and the launcher's summary say what the check says ---------------


def broken_everywhere() -> RunRecord:
    record = put_pair(clean_record(3), 7, (1, 2), 0.2)
    record = put_lambda(record, start_index(record) + 1, 2, 0.0)
    velocities = record.velocities_m_s.copy()
    velocities[40, 0, 2] = 3.5
    return changed(record, velocities_m_s=velocities)


def test_report_json_and_launcher_summary_agree_with_the_check() -> None:
    from swarm.launch.cli import print_summary

    record = broken_everywhere()
    expected = check_invariants(record)
    assert {v.invariant for v in expected} == {"collision", "lambda_bar", "velocity_bound"}
    report = build_report(record)
    assert list(report.violations) == expected and report.exit_code == EXIT_FAILED
    document = json.loads(json.dumps(report_to_json(report), allow_nan=False))
    assert document["verdict"] == "violated"
    for v, d in zip(expected, document["violations"], strict=True):
        assert (d["invariant"], d["detail"], d["subject"], d["first_subject"]) == (
            v.invariant, v.detail, v.subject, v.first_subject)
        for key in ("worst_value", "limit", "excess", "worst_time_s", "first_time_s",
                    "time_beyond_s"):
            assert d[key] == pytest.approx(getattr(v, key))
    out = io.StringIO()
    code = print_summary(record, Console(file=out, width=200))
    assert code == EXIT_FAILED
    text = out.getvalue()
    for v in expected:
        assert f"VIOLATION {v}" in text
    assert "verdict: FAILED (collision, lambda_bar, velocity_bound" in text
