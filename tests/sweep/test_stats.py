"""The Wilson interval and the per-cell figures of a sweep (swarm.sweep.stats)."""

from __future__ import annotations

import math

import pytest
from scipy.stats import binomtest

from swarm.sweep.stats import cell_stats, wilson_interval


@pytest.mark.parametrize("trials", [1, 2, 5, 20, 37, 200])
def test_wilson_interval_matches_scipy(trials: int) -> None:
    for successes in range(trials + 1):
        expected = binomtest(successes, trials).proportion_ci(0.95, method="wilson")
        low, high = wilson_interval(successes, trials)
        assert low == pytest.approx(expected.low, abs=1e-12)
        assert high == pytest.approx(expected.high, abs=1e-12)


def test_wilson_interval_other_confidence_and_edges() -> None:
    expected = binomtest(7, 9).proportion_ci(0.99, method="wilson")
    assert wilson_interval(7, 9, 0.99) == pytest.approx((expected.low, expected.high))
    assert wilson_interval(0, 0) == (0.0, 1.0)
    low, high = wilson_interval(20, 20)
    assert high == 1.0 and 0.83 < low < 0.84  # 20 of 20 is not "certainly 1"
    for bad in ((3, 2), (-1, 2)):
        with pytest.raises(ValueError):
            wilson_interval(*bad)


def _row(eps: float, verdict: str, margin: float | None, distance: float | None = 1.0) -> dict:
    return {"key": f"{eps}-{verdict}-{margin}", "params": {"gramian.epsilon": eps, "x": 1},
            "axes": ["gramian.epsilon"], "verdict": verdict, "min_lambda_margin": margin,
            "min_distance_m": distance}


def test_cell_stats_count_failed_apart_and_take_margins() -> None:
    rows = [_row(0.05, "OK", 0.3), _row(0.05, "OK", 0.1), _row(0.05, "VIOLATED", -0.2, 0.4),
            _row(0.05, "FAILED", None, None), _row(0.06, "FAILED", None, None)]
    first, second = cell_stats(rows)
    assert first.cell == (("gramian.epsilon", 0.05),)
    assert (first.missions, first.ok, first.violated, first.failed) == (4, 2, 1, 1)
    assert first.pass_rate == pytest.approx(2 / 3)
    assert first.interval == pytest.approx(wilson_interval(2, 3))
    assert first.median_margin == pytest.approx(0.1)
    assert first.worst_margin == pytest.approx(-0.2)
    assert first.worst_distance_m == pytest.approx(0.4)
    assert second.pass_rate is None and second.interval == (0.0, 1.0)
    assert second.median_margin is None and math.isclose(second.failed, 1)
