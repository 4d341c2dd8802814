"""Waiting in tests on a condition with a deadline, instead of sleeping a fixed time.

A fixed sleep is either too short on a loaded machine (the test fails for no reason) or
longer than needed everywhere (the suite is slower). ``wait_until`` polls the condition and
fails, saying what it waited for, only once the deadline has passed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_until(condition: Callable[[], T], timeout_s: float, what: str, *,
               period_s: float = 0.01, between: Callable[[], object] | None = None) -> T:
    """The first truthy value of ``condition()``, polled every ``period_s`` (first at once);
    an AssertionError naming ``what`` if none came within ``timeout_s``.

    ``between``: called instead of sleeping between two polls (a test that must pump a
    link or drain a queue for the condition to change; it should block for about
    ``period_s`` itself).
    """
    if not timeout_s > 0.0 or not period_s > 0.0:
        raise ValueError(f"timeout_s and period_s must be > 0, got {timeout_s!r}, {period_s!r}")
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        if between is None:
            time.sleep(period_s)
        else:
            between()
