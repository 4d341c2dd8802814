"""Thread-safe stores that turn Zenoh's callback deliveries into what an agent step reads.

- ``LatestValues`` (realtime mode): the newest value per source with its age; never a queue.
- ``StepMailbox`` (lockstep mode): values keyed (step, round, sender) and a blocking
  ``wait_for`` on a condition variable, pruned so memory stays bounded.

A subscription's callback (``swarm.net.subscriptions.subscribe``) only stores into them; the
agent's own thread reads.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable, Iterable
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestValues(Generic[T]):
    """Thread-safe latest value per source, with its receipt time (realtime mode).

    A source is any hashable: a drone id, or e.g. ``(drone, round)`` for consensus rounds.

    ``put(source, value, seq=step)`` ignores a value older (lower ``seq``) than the stored one,
    so a late out-of-order delivery never replaces newer data. Memory: one entry per source,
    at most ``max_sources`` sources. Every clock reading happens under the lock, so an age
    is never negative (a reading taken before a concurrent ``put`` stored a newer time would
    give e.g. a negative neighbour age, which the telemetry encoder refuses).
    """

    def __init__(self, *, clock: Callable[[], float] = time.monotonic,
                 max_sources: int = 4096) -> None:
        self._clock = clock
        self._max_sources = max_sources
        self._cond = threading.Condition()
        self._values: dict[Hashable, tuple[T, float, int | None]] = {}

    def put(self, source: Hashable, value: T, *, seq: int | None = None,
            arrived_s: float | None = None) -> bool:
        """Store ``value`` as the newest from ``source``; False if refused (older, or full).
        ``arrived_s``: when it arrived on this store's clock, if before now (a sample taken
        from a ring later, ``DrainedSubscriber.drain``); never later than now."""
        return self.put_many(((source, value, seq, arrived_s),)) == 1

    def put_many(self, items: Iterable[tuple[Hashable, T, int | None, float | None]]) -> int:
        """``put(source, value, seq=seq, arrived_s=arrived_s)`` for each item, under one lock
        and with one wake-up for all (e.g. every beacon of one relay); how many were stored."""
        stored = 0
        with self._cond:
            clock_s = self._clock()
            values = self._values
            for source, value, seq, arrived_s in items:
                old = values.get(source)
                if old is None and len(values) >= self._max_sources:
                    continue
                if old is not None and seq is not None and old[2] is not None and seq < old[2]:
                    continue
                values[source] = (value, clock_s if arrived_s is None
                                  else min(arrived_s, clock_s), seq)
                stored += 1
            if stored:
                self._cond.notify_all()
        return stored

    def get(self, source: Hashable) -> tuple[T, float] | None:
        """(value, age in seconds) or None if ``source`` never sent anything."""
        with self._cond:
            now = self._clock()
            entry = self._values.get(source)
        return None if entry is None else (entry[0], now - entry[1])

    def fresh(self, max_age_s: float) -> dict[Hashable, T]:
        """The values no older than ``max_age_s`` seconds, by source."""
        with self._cond:
            now = self._clock()
            return {s: v for s, (v, t, _) in self._values.items() if now - t <= max_age_s}

    def fresh_with_ages(self, max_age_s: float) -> dict[Hashable, tuple[T, float]]:
        """(value, age in seconds) of the values no older than ``max_age_s``, by source."""
        with self._cond:
            now = self._clock()
            return {s: (v, now - t) for s, (v, t, _) in self._values.items()
                    if now - t <= max_age_s}

    def ages(self) -> dict[Hashable, float]:
        with self._cond:
            now = self._clock()
            return {s: now - t for s, (_, t, _) in self._values.items()}

    def wait_for(self, sources: Iterable[Hashable], timeout_s: float, *,
                 min_seq: int | None = None) -> bool:
        """Block until every source in ``sources`` has a value (with ``seq >= min_seq`` if
        given); False at the deadline."""
        wanted = set(sources)

        def ready() -> bool:
            for s in wanted:
                entry = self._values.get(s)
                if entry is None or (min_seq is not None
                                     and (entry[2] is None or entry[2] < min_seq)):
                    return False
            return True

        with self._cond:
            return self._cond.wait_for(ready, timeout=timeout_s)

    def __len__(self) -> int:
        with self._cond:
            return len(self._values)


class StepMailbox(Generic[T]):
    """Thread-safe values keyed (step, round, sender) for lockstep consensus.

    - ``put`` keeps the FIRST value for a key; later duplicates are counted and ignored, so
      what ``wait_for`` returned can never change under the caller.
    - ``wait_for(step, round, senders, timeout_s)`` blocks on a condition variable until every
      requested sender has a value for (step, round) or the deadline passes, then returns
      exactly the requested senders that have one. ``put`` wakes a waiter only when its set
      is complete, not at every arrival (one wake-up per wait instead of one per sender).
    - Bounded memory: ``wait_for`` for step k drops every entry with a step below
      ``k - horizon_steps`` or above ``k + max_ahead_steps``, and ``put`` refuses such steps
      (and anything beyond ``max_entries``). Refusals are counted in ``refused``.
    """

    def __init__(self, *, horizon_steps: int = 2, max_ahead_steps: int = 4,
                 max_entries: int = 65536) -> None:
        for name, value in (("horizon_steps", horizon_steps),
                            ("max_ahead_steps", max_ahead_steps), ("max_entries", max_entries)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"StepMailbox: {name} must be an integer >= 0, got {value!r}")
        self.horizon_steps = horizon_steps
        self.max_ahead_steps = max_ahead_steps
        self.max_entries = max_entries
        self._cond = threading.Condition()
        self._boxes: dict[tuple[int, int], dict[int, T]] = {}
        self._entries = 0
        self._current: int | None = None  # the newest step anyone waited for
        self._closed = False
        self._waiters: dict[tuple[int, int], list[set[int]]] = {}  # what each wait needs
        self.refused = 0
        self.duplicates = 0

    def _in_window(self, step: int) -> bool:
        if self._current is None:
            return True
        return self._current - self.horizon_steps <= step <= self._current + self.max_ahead_steps

    def put(self, step: int, round: int, sender: int, value: T) -> bool:
        """Store ``value``; False if it was a duplicate or refused (outside the window, full)."""
        return self.put_many(((step, round, sender, value),)) == 1

    def put_many(self, items: Iterable[tuple[int, int, int, T]]) -> int:
        """``put(step, round, sender, value)`` for each item, under one lock, waking the
        waiters once (e.g. every beacon of one relay); how many were stored."""
        stored = 0
        complete = False
        with self._cond:
            for step, round, sender, value in items:
                if not self._in_window(step) or self._entries >= self.max_entries:
                    self.refused += 1
                    continue
                box = self._boxes.setdefault((step, round), {})
                if sender in box:
                    self.duplicates += 1
                    continue
                box[sender] = value
                self._entries += 1
                stored += 1
                complete = complete or any(
                    wanted <= box.keys() for wanted in self._waiters.get((step, round), ()))
            if complete:
                self._cond.notify_all()
        return stored

    def wait_for(self, step: int, round: int, senders: Iterable[int],
                 timeout_s: float) -> dict[int, T]:
        """What arrived for (step, round) from ``senders``: all of them, or what there is at
        the deadline or once ``close`` was called."""
        wanted = set(senders)
        deadline = time.monotonic() + max(0.0, timeout_s)
        key = (step, round)
        with self._cond:
            if self._current is None or step > self._current:
                self._current = step
                self._prune()
            waiters = self._waiters.setdefault(key, [])
            waiters.append(wanted)
            try:
                while True:
                    box = self._boxes.get(key, {})
                    found = {s: box[s] for s in wanted if s in box}
                    remaining = deadline - time.monotonic()
                    if len(found) == len(wanted) or remaining <= 0 or self._closed:
                        return found
                    self._cond.wait(remaining)
            finally:
                waiters.remove(wanted)
                if not waiters:
                    del self._waiters[key]

    def close(self) -> None:
        """From now on ``wait_for`` returns at once, including waits in progress (e.g. the
        mission ended: nothing more is coming)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def get(self, step: int, round: int) -> dict[int, T]:
        """What has arrived for (step, round) so far, without waiting (a copy)."""
        with self._cond:
            return dict(self._boxes.get((step, round), {}))

    def prune(self, current_step: int) -> None:
        """Advance the window to ``current_step`` without waiting."""
        with self._cond:
            if self._current is None or current_step > self._current:
                self._current = current_step
                self._prune()

    def _prune(self) -> None:
        for key in [k for k in self._boxes if not self._in_window(k[0])]:
            self._entries -= len(self._boxes.pop(key))

    def __len__(self) -> int:
        with self._cond:
            return self._entries
