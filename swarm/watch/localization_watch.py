"""Whether a drone's own λ̄ copies hold the localization guarantee, watched every step.
Pure: no I/O, no clock.

The guarantee the run is checked against (SPEC §7, ``[checks]``): from ``control.start_s`` on,
every drone's consensus copy of λ̄_j (the smallest eigenvalue of target j's weighted Gramian)
stays at or above ε − ``checks.lambda_tolerance``. A drone holds its copies itself, so it
knows at the very step a copy goes below that floor — for instance when the swarm lost a
drone and the survivors cannot make up for its view. ``LocalizationWatch.update`` compares the
copies with the floor each step and returns an event whenever a target goes below it
(a *breach* starts) or comes back; the agent logs each with its time, counts breaches in
telemetry (``lambda_breaches``, ``first_lambda_breach_s``) and shows the targets below the
floor now (``localization_status``), so the dashboard and the report say it at once. A copy
that is not a finite number is below the floor: it guarantees nothing.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass

STATUS_MAX_CHARS = 64  # the telemetry label's bound


@dataclass(frozen=True)
class LocalizationEvent:
    """Target ``target``'s λ̄ copy went below the floor (``below``) or came back above it."""

    time_s: float
    target: int
    below: bool
    lambda_bar: float  # the copy at this step
    floor: float  # ε − tolerance
    swarm_size: int  # drones in the membership at this step (0: not known)
    lowest: float  # lowest copy of the breach (on the way back: the whole breach's)
    since_s: float  # when the breach started

    def describe(self, drone_id: int) -> str:
        swarm = f" (swarm of {self.swarm_size})" if self.swarm_size else ""
        if self.below:
            return (f"drone {drone_id}: t = {self.time_s:.2f} s: cannot hold target "
                    f"{self.target} localized: λ̄ = {self.lambda_bar:.4f} < ε − tol = "
                    f"{self.floor:.4f}{swarm}")
        return (f"drone {drone_id}: t = {self.time_s:.2f} s: target {self.target} back to "
                f"λ̄ = {self.lambda_bar:.4f} ≥ ε − tol after {self.time_s - self.since_s:.2f} s "
                f"(lowest {self.lowest:.4f}){swarm}")


class LocalizationWatch:
    """λ̄ copies of ``n_targets`` targets against ε − ``tolerance``, from the steps where the
    control is active (``control.start_s`` on, as the run's checks)."""

    def __init__(self, n_targets: int, epsilon: float, tolerance: float) -> None:
        if n_targets < 1:
            raise ValueError(f"n_targets must be >= 1 (got {n_targets})")
        if not (math.isfinite(epsilon) and math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"epsilon and tolerance must be finite, tolerance >= 0 "
                             f"(got {epsilon!r}, {tolerance!r})")
        self.n_targets = n_targets
        self.floor = float(epsilon) - float(tolerance)
        self.breaches = 0  # breaches started so far (one per target and episode)
        self.first_breach_s: float | None = None
        self._since: dict[int, float] = {}  # targets below the floor now → since when
        self._lowest: dict[int, float] = {}

    @property
    def below(self) -> tuple[int, ...]:
        """The targets whose copy is below the floor now."""
        return tuple(sorted(self._since))

    def status(self) -> str:
        """"" while every copy holds; otherwise which targets are below and since when."""
        if not self._since:
            return ""
        parts = ", ".join(f"{j} since {self._since[j]:.1f} s" for j in self.below)
        return f"λ̄ < ε − tol: target {parts}"[:STATUS_MAX_CHARS]

    def update(self, time_s: float, lambda_bar: Collection[float], *, control_active: bool,
               swarm_size: int = 0) -> list[LocalizationEvent]:
        """This step's copies; an event per target that went below the floor or came back."""
        if len(lambda_bar) != self.n_targets:
            raise ValueError(f"expected {self.n_targets} λ̄ copies, got {len(lambda_bar)}")
        if not control_active:
            return []
        events = []
        for target, raw in enumerate(lambda_bar):
            value = float(raw)
            below = not value >= self.floor  # NaN is below
            if below:
                if target not in self._since:
                    self._since[target] = time_s
                    self._lowest[target] = value
                    self.breaches += 1
                    if self.first_breach_s is None:
                        self.first_breach_s = time_s
                    events.append(LocalizationEvent(time_s, target, True, value, self.floor,
                                                    swarm_size, value, time_s))
                elif not value >= self._lowest[target]:
                    self._lowest[target] = value
            elif target in self._since:
                since = self._since.pop(target)
                lowest = self._lowest.pop(target)
                events.append(LocalizationEvent(time_s, target, False, value, self.floor,
                                                swarm_size, lowest, since))
        return events
