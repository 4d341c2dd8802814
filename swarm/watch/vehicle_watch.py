"""The vehicle watched every step of the mission. Pure: no I/O, no clock.

During the mission an agent asked its autopilot for exactly one state: armed, in the mode
that takes setpoints (ArduPilot GUIDED, PX4 OFFBOARD), with a position estimate that keeps
coming. Anything else — a disarm, a failsafe's mode change (BRAKE, LAND, RTL, Hold, ...), a
pilot or ground station taking over, the position stream stopping — is something the agent
did not ask for. ``VehicleWatch.update`` compares the state each step with that one and
returns an event for every change: when the vehicle leaves the expected state, when what is
wrong changes, and when it is back. The agent logs each with its time, counts them in
telemetry (``vehicle_events``), shows the current one (``vehicle_status``) and applies the
configured policy (``vehicles.on_vehicle_event``):

- ``continue``: fly on degraded — the drone stays in the swarm (its beacon, consensus and
  camera go on; the autopilot may ignore the setpoints while it is elsewhere);
- ``leave``: the drone leaves the swarm: its agent ends (its vehicle gets the end action),
  the others see it lost and go on without it (``runtime.member_timeout_s``);
- ``end``: the mission ends: the agent ends with an error, which the launcher treats as a
  failed mission and stops everything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

VehicleEventPolicy = Literal["continue", "leave", "end"]
VEHICLE_EVENT_POLICIES: tuple[VehicleEventPolicy, ...] = ("continue", "leave", "end")
# A position sample older than this is a lost estimate (both firmwares stream at 50 Hz here;
# PX4's own offboard-loss timeout, COM_OF_LOSS_T, is 0.5 s as well).
POSITION_TIMEOUT_S = 0.5


@dataclass(frozen=True)
class VehicleEvent:
    """A change of what is wrong with the vehicle; ``problem`` "" = back as asked."""

    time_s: float
    problem: str
    previous: str

    def describe(self, drone_id: int) -> str:
        if not self.problem:
            return (f"drone {drone_id}: t = {self.time_s:.2f} s: vehicle back as asked "
                    f"(was: {self.previous})")
        return (f"drone {drone_id}: t = {self.time_s:.2f} s: vehicle not as asked, and not "
                f"by the agent: {self.problem}")


class VehicleWatch:
    """Expected: armed, in ``expected_mode`` (the link's ``setpoint_mode``), position samples
    younger than ``position_timeout_s``."""

    def __init__(self, expected_mode: str,
                 position_timeout_s: float = POSITION_TIMEOUT_S) -> None:
        if not expected_mode:
            raise ValueError("expected_mode must name a mode (got an empty string)")
        if not (math.isfinite(position_timeout_s) and position_timeout_s > 0):
            raise ValueError(f"position_timeout_s must be a finite number > 0 "
                             f"(got {position_timeout_s!r})")
        self.expected_mode = expected_mode
        self.position_timeout_s = float(position_timeout_s)
        self.problem = ""  # what is wrong now ("" = nothing)
        self.events = 0  # changes into or between problems (returns are logged, not counted)

    def update(self, time_s: float, *, armed: bool, mode: str,
               position_age_s: float | None) -> VehicleEvent | None:
        """This step's state; the event if what is wrong changed, else None."""
        problems = []
        if not armed:
            problems.append("disarmed")
        if mode != self.expected_mode:
            problems.append(f"mode {mode} (not {self.expected_mode})")
        if position_age_s is None or not position_age_s <= self.position_timeout_s:
            age = "none" if position_age_s is None else f"{position_age_s:.2f} s old"
            problems.append(f"position estimate {age}")
        problem = ", ".join(problems)
        if problem == self.problem:
            return None
        event = VehicleEvent(time_s, problem, self.problem)
        self.problem = problem
        if problem:
            self.events += 1
        return event
