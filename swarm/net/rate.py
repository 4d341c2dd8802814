"""A fixed-rate loop timer that says when a tick was missed (for realtime loops)."""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable


def freeze_heap() -> None:
    """Collect once, then move every surviving object out of the collector's reach.

    After the imports and the setup (numpy, zenoh, pymavlink, DAQP) a process holds hundreds
    of thousands of long-lived objects; a full collection walking them can stall a 20 ms loop.
    Frozen, they are never scanned again and the loop's collections see only new objects.
    """
    gc.collect()
    gc.freeze()


class RateLimiter:
    """Ticks every ``period_s`` on a fixed schedule t0 + k·period of the monotonic clock.

    ``sleep()`` waits for the next tick. A tick reached after its time is *late*: counted, and
    the schedule keeps its phase (a tick already due fires at once), so that k ticks span k
    periods of wall time. That is what keeps realtime processes on one clock: the world's sim
    time k·ΔT and each agent's filter time (one ΔT prediction per step) both follow the wall
    clock instead of drifting apart by every delay: a loop that fell behind runs its ticks
    back to back until it is on time again (a step costs ~1 ms of a 20 ms period, so it
    catches up fast). Only after a stall of more than ``max_behind_periods`` (default 1 s at
    50 Hz: the process was stopped, not merely preempted) is the schedule restarted from now,
    counted in ``restarts``.

    ``first_tick_s``: when the first tick was (on ``clock``; default now): the schedule is
    first_tick_s + k·period, which sets its phase.
    """

    def __init__(self, period_s: float, *, max_behind_periods: float = 50.0,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 first_tick_s: float | None = None) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"period_s must be a finite number > 0 (got {period_s})")
        if not max_behind_periods >= 1:
            raise ValueError(f"max_behind_periods must be ≥ 1 (got {max_behind_periods})")
        self.period_s = period_s
        self.max_behind_s = max_behind_periods * period_s
        self._clock = clock
        self._sleep = sleep
        if first_tick_s is not None and not math.isfinite(first_tick_s):
            raise ValueError(f"first_tick_s must be finite (got {first_tick_s})")
        self._next = (clock() if first_tick_s is None else first_tick_s) + period_s
        self.ticks = 0
        self.late_ticks = 0
        self.restarts = 0
        self.last_lateness_s = 0.0

    def remaining(self) -> float:
        """Seconds left before the next tick (negative when already late)."""
        return self._next - self._clock()

    def sleep(self) -> bool:
        """Wait for the next tick; returns True if this tick was late."""
        self.ticks += 1
        now = self._clock()
        lateness = now - self._next
        self.last_lateness_s = max(lateness, 0.0)
        if lateness <= 0:
            self._sleep(-lateness)
            self._next += self.period_s
            return False
        self.late_ticks += 1
        if lateness > self.max_behind_s:
            self.restarts += 1
            self._next = now + self.period_s
        else:
            self._next += self.period_s
        return True
