"""A fixed-rate loop timer that says when a tick was missed (for realtime loops)."""

from __future__ import annotations

import time


class RateLimiter:
    """Ticks every ``period_s`` on the monotonic clock.

    ``sleep()`` waits for the next tick. If the work of a tick ran past the next tick, the
    tick is *late*: it is counted, and the schedule restarts from now instead of firing a
    burst of catch-up ticks (a control loop wants fresh data, not old ticks).
    """

    def __init__(self, period_s: float, clock=time.monotonic) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0 (got {period_s})")
        self.period_s = period_s
        self._clock = clock
        self._next = clock() + period_s
        self.late_ticks = 0
        self.last_lateness_s = 0.0

    def remaining(self) -> float:
        """Seconds left before the next tick (negative when already late)."""
        return self._next - self._clock()

    def sleep(self) -> bool:
        """Wait for the next tick; returns True if this tick was late."""
        now = self._clock()
        lateness = now - self._next
        self.last_lateness_s = max(lateness, 0.0)
        if lateness > 0:
            self.late_ticks += 1
            self._next = now + self.period_s
            return True
        time.sleep(-lateness)
        self._next += self.period_s
        return False
