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
import functools
import io
import itertools
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from rich.console import Console

from swarm.errors import EXIT_FAILED, EXIT_INCOMPLETE, EXIT_OK
from swarm.launch.cli import print_summary
from swarm.observe.report import build_report, report_to_json, verdict_line
from swarm.runs import checks
from swarm.runs.checks import (
    Coverage,
    DroneSummary,
    TargetSummary,
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


@functools.cache  # a frozen config, loaded once: the mutation judge runs these tests ~1000 times
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


# -- what mutation testing found untested (issue 46, point 2; docs/mutation.md) ------------
# Each test below kills mutants of swarm/runs/checks.py that the tests above let survive:
# a line is asserted whole where a word of it could change, and records are shaped so that
# a wrong axis, index or offset gives a different answer (N != M, K != 2 * k0, ...).


def starting_at(record: RunRecord, start_s: float) -> RunRecord:
    config = record.config
    return dataclasses.replace(record, config=dataclasses.replace(
        config, control=dataclasses.replace(config.control, start_s=start_s)))


def test_start_index_is_the_first_step_at_or_after_start_despite_rounding() -> None:
    record = clean_record(2)  # ΔT = 0.02 s
    assert start_index(record) == 50  # 1 s
    assert start_index(starting_at(record, 0.14)) == 7  # 0.14 / 0.02 = 7.000000000000001
    assert start_index(starting_at(record, 0.58)) == 29  # 28.999999999999996
    assert start_index(starting_at(record, 0.0)) == 0


def test_nan_reductions_of_nothing_one_value_and_only_missing_values() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an all-NaN slice is NaN without a RuntimeWarning
        for reduce in (checks.nanmin, checks.nanmax):
            assert math.isnan(reduce(np.array([])))
            assert reduce(np.array([2.5])) == 2.5
            assert math.isnan(reduce(np.array([np.nan, np.nan])))
        assert checks.nanmin(np.array([3.0, np.nan, -1.0])) == -1.0
        assert checks.nanmax(np.array([3.0, np.nan, -1.0])) == 3.0


def test_coverage_counts_what_never_arrived_per_drone_and_per_step() -> None:
    record = clean_record(3)
    velocities, lam = record.velocities_m_s.copy(), record.lambda_bar.copy()
    positions, targets = record.drone_positions_m.copy(), record.target_positions_m.copy()
    velocities[5:7, 1] = lam[5:7, 1] = np.nan  # drone 1's telemetry of steps 5 and 6 lost
    velocities[7, 2] = np.nan  # a command NaN but λ̄ there: received, not missing
    lam[8, 0] = np.nan  # λ̄ NaN but a command there: received
    positions[9] = targets[9] = np.nan  # no ground truth at step 9
    positions[10, 0] = np.nan  # one drone's position: the step's truth is there
    targets[11] = np.nan  # the targets' only: there too
    record = changed(record, velocities_m_s=velocities, lambda_bar=lam,
                     drone_positions_m=positions, target_positions_m=targets)
    assert checks.coverage(record) == Coverage(
        steps=100, drone_steps=300, missing_telemetry=2, missing_truth=1,
        missing_per_drone=(0, 2, 0), planned_steps=100)
    assert np.flatnonzero(checks.truth_missing(record)).tolist() == [9]
    assert np.argwhere(checks.telemetry_missing(record)).tolist() == [[5, 1], [6, 1]]


def test_last_present_and_final_values_take_each_drones_last_sample() -> None:
    assert checks.last_present(np.empty((0, 3))) is None
    assert checks.last_present(np.full((4, 2), np.nan)) is None
    assert checks.last_present(np.array([7.0])) == 0
    assert checks.last_present(np.array([np.nan, 1.0, 2.0, np.nan])) == 2
    series = np.full((5, 3), np.nan)
    series[0, 1], series[1, 0], series[3, 2] = 0.5, 1.0, 2.0  # step 3: one component only
    assert checks.last_present(series) == 3
    per_drone = np.full((4, 3, 2), np.nan)  # (K, N, M): N != M
    per_drone[:, 0] = [[1, 2], [3, 4], [5, 6], [7, 8]]
    per_drone[2, 2] = [9, 10]  # drone 2's last sample at step 2; drone 1 has none
    final = checks.final_values(per_drone)
    assert final.dtype == np.float64 and final.shape == (3, 2)
    np.testing.assert_array_equal(final, [[7, 8], [np.nan, np.nan], [9, 10]])


def summaries_record() -> RunRecord:
    """case2 (two targets), 4 drones, each figure of the summaries set apart: values before
    control.start_s that would win if counted, exactly-at-the-threshold values, a drone with
    no telemetry at all."""
    record = clean_record(4, case="case2")
    k0 = start_index(record)
    eps = record.config.gramian.epsilon
    lam = record.lambda_bar.copy()
    lam[k0 - 1, 0, 0] = -1.0  # warm-up: not counted
    lam[k0 + 4, 1, 0] = 0.04
    lam[k0 + 4, 2, 0] = 0.03  # the same step: counted once
    lam[k0 + 5, 2, 0] = 0.045
    lam[k0 + 6, 2, 0] = eps  # at ε: not below
    lam[:, 3] = np.nan  # drone 3: no telemetry
    lam[k0 + 1, 0, 1] = np.nan  # one λ̄ of target 1 missing (its command arrived)
    true_min, measured_min = record.true_lambda_min.copy(), record.measured_lambda_min.copy()
    true_min[k0 - 1, 0], true_min[k0 + 2, 0] = 0.01, 0.5
    measured_min[k0 - 1, 1], measured_min[k0 + 3, 1] = 0.02, 0.7
    estimates = record.estimates.copy()
    estimates[k0 + 10, 1, 0, 0] = 0.3  # one error of 0.3 m after the start
    estimates[-1, 2, 1, 1] = 0.4  # target 1's final error: drone 2's last
    estimates[k0 - 1, 0, 0, 0] = 9.0  # before the start: not in the RMS
    weights = record.weights.copy()
    weights[-1, 0] = [SENSING, 0.05]  # drone 0 idle: w <= 0.1 for both targets
    weights[-1, 1] = [0.5, SENSING]
    weights[:, 3] = np.nan
    velocities = record.velocities_m_s.copy()
    velocities[-1, 1] = [0.0, 3.0, 4.0]  # drone 1's last command: 5 m/s
    velocities[-2:, 2] = np.nan  # drone 2's last command at step K - 3
    velocities[-3, 2] = [0.0, 0.0, 2.0]
    velocities[:, 3] = np.nan
    weights[-3, 2] = [0.2, 0.3]
    step_us = record.step_us.copy()
    step_us[:, 0] = np.arange(1.0, 101.0)  # p99 = 99.01, p100 would be 100
    step_us[:, 3] = np.nan
    fallbacks = record.qp_fallback.copy()
    fallbacks[[3, 60, 61], 1] = True
    bearing = np.full_like(record.bearing_errors, 0.25)  # not a formation: never reported
    return changed(record, lambda_bar=lam, true_lambda_min=true_min,
                   measured_lambda_min=measured_min, estimates=estimates, weights=weights,
                   velocities_m_s=velocities, step_us=step_us, qp_fallback=fallbacks,
                   bearing_errors=bearing)


SENSING = checks.SENSING_WEIGHT


def assert_same(got: object, want: object) -> None:
    """Two summaries field by field: floats (and tuples of them) to 1e-12, NaN equal to NaN."""
    for f in dataclasses.fields(want):  # type: ignore[arg-type]
        a, b = getattr(got, f.name), getattr(want, f.name)
        if isinstance(b, float) or (isinstance(b, tuple) and b):
            assert a == pytest.approx(b, rel=1e-12, abs=1e-12, nan_ok=True), f.name
        else:
            assert a == b and type(a) is type(b), f.name


def test_target_summaries_count_after_the_start_and_the_final_samples() -> None:
    record = summaries_record()
    eps = record.config.gramian.epsilon
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        first, second = checks.summarize_targets(record)
    assert_same(first, TargetSummary(
        target=0, min_lambda_bar_margin=0.03 - eps, time_below_epsilon_s=2 * 0.02,
        min_true_lambda_margin=0.5 - eps, min_measured_lambda=1.0,
        final_position_error_m=0.0, rms_position_error_m=math.sqrt(0.09 / (50 * 4)),
        drones_sensing_final=2, missing_samples=100,  # drones 1, 2; 0 is at 0.1
        lambda_copy_spread=1.0 - 0.03))  # drone 2's 0.03 beside 1.0 (the warm-up's −1 not)
    assert_same(second, TargetSummary(
        target=1, min_lambda_bar_margin=1.0 - eps, time_below_epsilon_s=0.0,
        min_true_lambda_margin=1.0 - eps, min_measured_lambda=0.7,
        final_position_error_m=0.4, rms_position_error_m=math.sqrt(0.16 / (50 * 4)),
        drones_sensing_final=1, missing_samples=101, lambda_copy_spread=0.0))


def test_the_copy_spread_is_the_widest_step_its_missing_samples_left_out() -> None:
    copies = np.array([[0.1, 0.3, np.nan], [0.2, 0.2, 0.25], [np.nan] * 3, [-0.5, 0.5, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert checks.copy_spread(copies) == pytest.approx(1.0, abs=1e-15)
        assert checks.copy_spread(copies[:3]) == pytest.approx(0.2, abs=1e-15)
        assert math.isnan(checks.copy_spread(copies[2:3]))
        assert math.isnan(checks.copy_spread(np.zeros((0, 3))))


def test_a_record_cut_short_before_the_start_has_no_figure_after_it() -> None:
    record = clean_record(2, steps=40)  # control.start_s is step 50
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        [summary] = checks.summarize_targets(record)
    assert math.isnan(summary.rms_position_error_m)
    assert math.isnan(summary.min_lambda_bar_margin) and summary.time_below_epsilon_s == 0.0


def test_drone_summaries_take_each_drones_last_telemetry() -> None:
    record = summaries_record()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a drone without telemetry gives NaN, not warnings
        summaries = checks.summarize_drones(record)
    expected = [
        DroneSummary(0, 0.1, (SENSING, 0.05), True, 0, 50.5, 99.01, None, 0),
        DroneSummary(1, 5.0, (0.5, SENSING), False, 3, 50.0, 50.0, None, 0),
        DroneSummary(2, 2.0, (0.2, 0.3), False, 0, 50.0, 50.0, None, 0),
        DroneSummary(3, math.nan, (math.nan, math.nan), False, 0, math.nan, math.nan, None,
                     100),
    ]
    assert len(summaries) == 4
    for got, want in zip(summaries, expected, strict=True):
        assert_same(got, want)


def test_a_formation_reports_each_drones_last_bearing_error() -> None:
    record = summaries_record()
    control = dataclasses.replace(record.config.control, task="bearing_formation")
    bearing = record.bearing_errors.copy()
    bearing[-1, 1] = 0.75
    bearing[-4:, 2] = np.nan  # drone 2's last bearing error at step K - 5
    bearing[-5, 2] = 0.125
    bearing[:, 3] = np.nan
    record = changed(dataclasses.replace(
        record, config=dataclasses.replace(record.config, control=control)),
        bearing_errors=bearing)
    errors = [s.final_bearing_error for s in checks.summarize_drones(record)]
    assert errors == [0.25, 0.75, 0.125, None]


def test_min_envelope_margins_are_each_kinds_closest_approach() -> None:
    record = clean_record(3, case="case2_envelope")
    ceiling = record.config.safety.params.ceiling_m
    positions = record.drone_positions_m.copy()
    positions[20, 1, 2] = ceiling - 0.25
    margins = checks.min_envelope_margins(changed(record, drone_positions_m=positions))
    assert margins["ceiling"] == 0.25
    assert set(margins) == set(checks.envelope_margins((0.0, 0.0, 0.0),
                                                       record.config.safety.params))


def test_every_envelope_kind_without_a_position_is_said_not_checked() -> None:
    record = clean_record(3, case="case2_envelope")
    record = changed(record, drone_positions_m=np.full_like(record.drone_positions_m, np.nan))
    kinds = list(checks.envelope_margin_series(record))
    assert len(kinds) >= 2
    assert [v for v in check_invariants(record) if v.invariant == "envelope"] == [
        Violation("envelope", f"{kind}: not checked: no drone position") for kind in kinds]


def test_the_not_checked_lines_are_exact() -> None:
    nowhere = clean_record(2)
    nowhere = changed(nowhere, drone_positions_m=np.full_like(nowhere.drone_positions_m,
                                                              np.nan),
                      velocities_m_s=np.full_like(nowhere.velocities_m_s, np.nan))
    lines = {v.invariant: v.detail for v in check_invariants(nowhere)}
    assert lines["collision"] == "not checked: no step with two drone positions"
    assert lines["velocity_bound"] == "not checked: no command in the record"


def test_each_violation_line_is_exact() -> None:
    record = broken_everywhere()  # case1: Δ = 0.5 m, tol 0.001 m; ε = 0.05, tol 0.005
    lines = {v.invariant: v.detail for v in check_invariants(record)}
    assert lines == {
        "collision": "min pairwise distance 0.2000 m < Δ − tol = 0.4990 m (by 0.2990 m): "
                     "drones 1 and 2 at t = 0.14 s; first below at t = 0.14 s (drones 1 and "
                     "2), below for 0.02 s",
        "lambda_bar": "target 0: drone 2 has λ̄ = 0.0000 < ε − tol = 0.0450 (by 0.0450) at "
                      "t = 1.02 s; first below at t = 1.02 s (target 0, drone 2), below for "
                      "0.02 s",
        "velocity_bound": "a command reaches |u_k| = 3.5000 m/s > u_max = 3.0 m/s (drone 0, "
                          "u_z) at t = 0.80 s; first above at t = 0.80 s (drone 0, u_z), "
                          "above for 0.02 s",
    }


def test_the_envelope_line_is_exact() -> None:
    record = clean_record(3, case="case2_envelope")
    ceiling = record.config.safety.params.ceiling_m
    tolerance = record.config.checks.envelope_tolerance_m
    positions = record.drone_positions_m.copy()
    positions[30, 2, 2] = ceiling + 0.5
    [v] = [v for v in check_invariants(changed(record, drone_positions_m=positions))
           if v.invariant == "envelope"]
    assert v.detail == (f"drone 2 went 0.5000 m beyond the ceiling (tolerance {tolerance} m) "
                        "at t = 0.60 s; first beyond at t = 0.60 s (ceiling, drone 2), beyond "
                        "for 0.02 s")


def test_finite_lines_name_a_target_and_say_whether_a_position_is_infinite() -> None:
    base = clean_record(3, case="case2")
    targets = base.target_positions_m.copy()
    targets[3, 1, 0] = np.inf
    v = only(check_invariants(changed(base, target_positions_m=targets)), "finite")
    assert (v.subject, v.first_subject) == ("target 1's position (inf)",) * 2
    assert v.detail == ("a position, command, estimate or λ̄ is NaN/inf (0 received samples "
                        "non-finite, a position is inf); first: target 1's position (inf) at "
                        "t = 0.06 s")
    estimates = base.estimates.copy()
    estimates[4, 0, 1, 2] = np.nan
    v = only(check_invariants(changed(base, estimates=estimates)), "finite")
    assert v.first_subject == "drone 0's estimate"
    assert v.detail == ("a position, command, estimate or λ̄ is NaN/inf (1 received samples "
                        "non-finite); first: drone 0's estimate at t = 0.08 s")


def test_lambda_bar_checks_every_target_after_one_not_checked_or_held() -> None:
    base = clean_record(3, case="case2")
    k0 = start_index(base)
    floor = lambda_floor(base.config)
    lam = base.lambda_bar.copy()
    lam[k0 + 2, 1, 1] = floor - 0.01  # target 1 breached; target 0 holds
    v = only(check_invariants(changed(base, lambda_bar=lam)), "lambda_bar")
    assert v.subject == "target 1, drone 1"
    lam[k0:, :, 0] = np.nan  # target 0 not checked
    found = [v for v in check_invariants(changed(base, lambda_bar=lam))
             if v.invariant == "lambda_bar"]
    assert [v.subject or v.detail.split(":")[0] for v in found] == ["target 0",
                                                                    "target 1, drone 1"]


def test_lambda_bar_times_are_counted_from_the_records_first_step() -> None:
    base = clean_record(3, steps=80)  # not twice control.start_s: an offset shows
    k0 = start_index(base)
    v = only(check_invariants(put_lambda(base, k0 + 3, 1, 0.0)), "lambda_bar")
    assert v.worst_time_s == v.first_time_s == float(base.times_s[k0 + 3])


def test_velocity_bound_names_the_drone_and_axis_of_the_worst_command() -> None:
    base = clean_record(3)
    u_max = base.config.control.u_max_m_s
    velocities = base.velocities_m_s.copy()
    velocities[10, 1, 0] = u_max + 1e-9  # the check's own rounding margin: held
    assert check_invariants(changed(base, velocities_m_s=velocities)) == []
    velocities[10, 1, 0] = u_max + 0.1  # drone 1, u_x: column 3
    velocities[12, 2, 1] = -(u_max + 0.5)  # the worst, later
    v = only(check_invariants(changed(base, velocities_m_s=velocities)), "velocity_bound")
    assert (v.subject, v.first_subject) == ("drone 2, u_y", "drone 1, u_x")
    assert v.worst_value == pytest.approx(u_max + 0.5)


def test_a_drone_without_telemetry_in_a_record_shorter_than_the_swarm() -> None:
    record = clean_record(4, steps=2)
    velocities, lam = record.velocities_m_s.copy(), record.lambda_bar.copy()
    velocities[:, 3] = lam[:, 3] = np.nan
    last = checks.summarize_drones(changed(record, velocities_m_s=velocities, lambda_bar=lam))[3]
    assert math.isnan(last.final_speed_m_s) and last.missing_samples == 2


def test_the_lambda_bar_line_says_by_how_much() -> None:
    record = put_lambda(clean_record(3), 60, 1, 0.02)  # ε − tol = 0.045
    v = only(check_invariants(record), "lambda_bar")
    assert v.detail.startswith("target 0: drone 1 has λ̄ = 0.0200 < ε − tol = 0.0450 (by "
                               "0.0250) at t = 1.20 s")
