"""An invariant not held, as the run's checks report it (``swarm.runs.checks``,
``swarm.runs.network``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Violation:
    """One invariant not held: which (``subject``: the pair, drone, target or boundary), when
    (the worst point, and the first step past the limit) and by how much, as one line
    (``detail``) and as fields. An invariant that could not be checked at all has only
    ``detail``."""

    invariant: str
    detail: str
    subject: str = ""  # e.g. "drones 1 and 3", "target 0, drone 5", "ceiling, drone 2"
    worst_value: float | None = None  # the checked quantity at its worst point
    limit: float | None = None  # the bound it must respect (tolerance included)
    excess: float | None = None  # how far the worst point is past the limit (> 0)
    worst_time_s: float | None = None
    first_time_s: float | None = None  # the first step past the limit
    first_subject: str = ""  # who crossed first
    time_beyond_s: float | None = None  # steps past the limit × ΔT

    def __str__(self) -> str:
        return f"{self.invariant}: {self.detail}"
