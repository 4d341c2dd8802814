"""The vehicle watched every step (swarm.watch.vehicle_watch): what the agent did not ask for."""

from __future__ import annotations

import math

import pytest

from swarm.watch.vehicle_watch import POSITION_TIMEOUT_S, VehicleWatch


@pytest.mark.parametrize("mode", ["GUIDED", "OFFBOARD"])
def test_only_changes_are_events_and_every_problem_is_named(mode: str) -> None:
    watch = VehicleWatch(mode)
    assert watch.update(0.0, armed=True, mode=mode, position_age_s=0.02) is None
    assert watch.update(0.02, armed=True, mode=mode, position_age_s=0.3) is None
    event = watch.update(1.5, armed=True, mode="LOITER", position_age_s=0.02)
    assert event is not None and event.time_s == 1.5 and "mode LOITER" in event.problem
    assert watch.events == 1 and "not by the agent: mode LOITER" in event.describe(2)
    assert watch.update(1.52, armed=True, mode="LOITER", position_age_s=0.02) is None
    event = watch.update(2.0, armed=False, mode="LOITER", position_age_s=0.02)
    assert event is not None and "disarmed" in event.problem and "mode LOITER" in event.problem
    assert watch.events == 2
    event = watch.update(3.0, armed=True, mode=mode, position_age_s=0.02)
    assert event is not None and event.problem == "" and "back as asked" in event.describe(2)
    assert watch.events == 2 and watch.problem == ""


def test_a_position_estimate_that_stops_is_an_event() -> None:
    watch = VehicleWatch("OFFBOARD")
    event = watch.update(4.0, armed=True, mode="OFFBOARD", position_age_s=POSITION_TIMEOUT_S + 0.1)
    assert event is not None and "position estimate 0.60 s old" in event.problem
    event = watch.update(4.1, armed=True, mode="OFFBOARD", position_age_s=math.nan)
    assert event is None or "position estimate" in event.problem
    assert watch.update(5.0, armed=True, mode="OFFBOARD", position_age_s=None) is not None


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="expected_mode"):
        VehicleWatch("")
    with pytest.raises(ValueError, match="position_timeout_s"):
        VehicleWatch("OFFBOARD", position_timeout_s=0.0)


# -- what mutation testing found untested (issue 46, point 2; docs/mutation.md) ------------


def test_each_event_says_exactly_what_is_wrong_and_what_was() -> None:
    watch = VehicleWatch("GUIDED")
    event = watch.update(1.0, armed=False, mode="LOITER", position_age_s=None)
    assert event is not None
    assert (event.problem, event.previous) == (
        "disarmed, mode LOITER (not GUIDED), position estimate none", "")
    event = watch.update(2.0, armed=True, mode="LOITER", position_age_s=0.02)
    assert event is not None
    assert (event.problem, event.previous) == (
        "mode LOITER (not GUIDED)", "disarmed, mode LOITER (not GUIDED), position estimate none")
    back = watch.update(3.0, armed=True, mode="GUIDED", position_age_s=0.02)
    assert back is not None and (back.problem, back.previous) == ("", "mode LOITER (not GUIDED)")


def test_a_position_exactly_the_timeout_old_is_still_fresh() -> None:
    watch = VehicleWatch("OFFBOARD")
    assert watch.update(0.0, armed=True, mode="OFFBOARD",
                        position_age_s=POSITION_TIMEOUT_S) is None


def test_an_empty_mode_is_refused_with_its_line() -> None:
    with pytest.raises(ValueError,
                       match=r"^expected_mode must name a mode \(got an empty string\)$"):
        VehicleWatch("")
