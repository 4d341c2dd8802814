"""The realtime loop timer keeps a fixed phase, counts late ticks and restarts after stalls."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from swarm.net.rate import RateLimiter


class FakeTime:
    """A clock that only moves when the loop works or sleeps."""

    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds >= 0
        self.slept.append(seconds)
        self.now += seconds


def limiter(fake: FakeTime, period: float = 0.02, **kwargs) -> RateLimiter:
    return RateLimiter(period, clock=fake.clock, sleep=fake.sleep, **kwargs)


def test_on_time_ticks_sleep_to_the_schedule() -> None:
    fake = FakeTime()
    rate = limiter(fake)
    for k in range(1, 6):
        fake.now += 0.005  # work
        assert rate.sleep() is False
        assert fake.now == pytest.approx(100.0 + 0.02 * k)
    assert rate.late_ticks == 0


@given(st.lists(st.floats(0.0, 0.09), min_size=1, max_size=200))
def test_late_ticks_keep_the_phase(works: list[float]) -> None:
    """Work up to 4.5 periods long, no restart: after the loop catches up, the clock sits
    exactly on the schedule t0 + k·period (no drift, whatever the delays)."""
    fake = FakeTime()
    period = 0.02
    rate = limiter(fake, period, max_behind_periods=1e9)
    late = 0
    for work in works:
        fake.now += work
        late += rate.sleep()
    assert rate.late_ticks == late
    assert rate.restarts == 0
    while rate.sleep():  # idle ticks: catch up
        pass
    ticks = rate.ticks
    assert fake.now == pytest.approx(100.0 + period * ticks, abs=1e-9)


def test_a_late_tick_is_counted_and_the_next_one_is_not_postponed() -> None:
    fake = FakeTime()
    rate = limiter(fake)
    fake.now += 0.025  # 5 ms past the first tick
    assert rate.sleep() is True
    assert rate.last_lateness_s == pytest.approx(0.005)
    fake.now += 0.001
    assert rate.sleep() is False
    assert fake.now == pytest.approx(100.04)  # second tick on schedule, not at 100.045


def test_a_stall_restarts_the_schedule_instead_of_bursting() -> None:
    fake = FakeTime()
    rate = limiter(fake, max_behind_periods=5)
    fake.now += 1.0  # 49 periods behind
    assert rate.sleep() is True
    assert rate.restarts == 1
    assert rate.sleep() is False
    assert fake.now == pytest.approx(101.02)


@pytest.mark.parametrize("period", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_period_is_refused(period: float) -> None:
    with pytest.raises(ValueError, match="period_s"):
        RateLimiter(period)


def test_the_first_tick_sets_the_phase() -> None:
    """``first_tick_s`` ahead of now: the schedule is first_tick + k·period; behind now (the
    loop started late): the first sleep is late and the schedule keeps that phase."""
    fake = FakeTime()
    rate = limiter(fake, first_tick_s=100.013)
    assert rate.sleep() is False
    assert fake.now == pytest.approx(100.033)
    late = limiter(fake, first_tick_s=fake.now - 0.025)
    assert late.sleep() is True
    fake.now += 0.002
    assert late.sleep() is False
    assert fake.now == pytest.approx(100.033 - 0.025 + 0.04)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_first_tick_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="first_tick_s must be finite"):
        limiter(FakeTime(), first_tick_s=bad)
