"""tests.helpers.waiting: ``wait_until`` returns the condition's first truthy value, and says
what it waited for when the time is up."""

from __future__ import annotations

import itertools
import time

import pytest

from tests.helpers.waiting import wait_until


def test_the_first_truthy_value_is_returned_without_waiting_longer() -> None:
    counter = itertools.count()
    started = time.monotonic()
    assert wait_until(lambda: next(counter) >= 3 and "ready", 5.0, "the third poll") == "ready"
    assert next(counter) == 4  # polled four times, then stopped
    assert time.monotonic() - started < 1.0


def test_between_replaces_the_sleep() -> None:
    pumped: list[int] = []
    assert wait_until(lambda: len(pumped) == 2, 5.0, "two pumps",
                      between=lambda: pumped.append(1))
    assert pumped == [1, 1]


def test_a_timeout_names_what_was_awaited() -> None:
    started = time.monotonic()
    with pytest.raises(AssertionError, match=r"^timed out after 0.05 s waiting for the answer$"):
        wait_until(lambda: None, 0.05, "the answer")
    assert 0.05 <= time.monotonic() - started < 1.0


@pytest.mark.parametrize(("timeout_s", "period_s"), [(0.0, 0.01), (1.0, 0.0), (-1.0, 0.01)])
def test_a_wait_without_time_is_refused(timeout_s: float, period_s: float) -> None:
    with pytest.raises(ValueError, match="must be > 0"):
        wait_until(lambda: True, timeout_s, "anything", period_s=period_s)
