"""Fault injection on a Zenoh link (a test option, off by default): ``LinkFaults`` says what
to do to one key's outgoing messages, ``FaultyPublisher`` does it — drops a share of them at
random, or sends each a number of steps late, as a lossy or slow radio link would."""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass
from typing import Any

import zenoh


@dataclass(frozen=True)
class LinkFaults:
    """What a ``FaultyPublisher`` does to the messages put through it (a test option)."""

    drop_rate: float = 0.0  # each message is lost with this probability
    delay_steps: int = 0  # each message that is not lost goes out this many steps late
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.drop_rate) and 0.0 <= self.drop_rate < 1.0):
            raise ValueError(f"drop rate must be in [0, 1), got {self.drop_rate!r}")
        if self.delay_steps < 0:
            raise ValueError(f"delay must be >= 0 steps, got {self.delay_steps!r}")

    @property
    def active(self) -> bool:
        return self.drop_rate > 0.0 or self.delay_steps > 0


class FaultyPublisher:
    """Puts messages with a Zenoh timestamp of when they were *sent* (``put_stamped``), after
    losing some at random and holding the others back a number of steps: a receiver sees
    what a lossy, slow link would deliver, the age of the data included.

    ``advance(step)`` at the start of each step sends what is due: a message put during step
    k goes out at the start of step k + ``delay_steps``. Used from one thread (the step's).
    """

    def __init__(self, session: zenoh.Session, publisher: zenoh.Publisher,
                 faults: LinkFaults) -> None:
        self._session, self._publisher, self.faults = session, publisher, faults
        self._random = random.Random(faults.seed)
        self._held: deque[tuple[int, Any, bytes]] = deque()  # (due step, timestamp, payload)
        self._step = 0
        self.offered = self.sent = self.dropped = self.delayed = 0

    def advance(self, step: int) -> None:
        self._step = step
        while self._held and self._held[0][0] <= step:
            _due, stamp, payload = self._held.popleft()
            self._publisher.put(payload, timestamp=stamp)
            self.sent += 1

    def put(self, payload: bytes) -> None:
        stamp = self._session.new_timestamp()
        self.offered += 1
        if self._random.random() < self.faults.drop_rate:
            self.dropped += 1
        elif self.faults.delay_steps:
            self._held.append((self._step + self.faults.delay_steps, stamp, payload))
            self.delayed += 1
        else:
            self._publisher.put(payload, timestamp=stamp)
            self.sent += 1
