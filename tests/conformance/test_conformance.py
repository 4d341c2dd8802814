"""One MAVLink dialogue per flavour, against the real autopilot and against our emulator.

``tests/conformance/dialogue.py`` holds the dialogues (what is sent, what must come back,
and the bands of what is measured); this runs each against

* ``sitl``: the real firmware in SITL (ArduCopter, PX4 with SIH;
  ``tests/helpers/sitl_tools.py``), found
  through ``VIGIL_ARDUCOPTER`` / ``VIGIL_PX4`` or in ``../shared/autopilots``; skipped, saying
  why, when absent; marked slow;
* ``emulator``: ``sim_world``'s ``EmulatedVehicle`` in a ``VehicleFleet`` of one on real UDP
  (``emulated_target``), starting on the ground with the flavour's measured velocity
  response.

Both must give the same answers and land in the same bands. Run with ``-s`` to see the
conversation and each figure. Each SITL boots while its flavour's emulator dialogue runs, and
ArduCopter's dialogue flies beside it (``conftest.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from sim_world.vehicle import Flavour
from tests.conformance.conftest import Fly, SitlFlights
from tests.conformance.dialogue import Record, ardupilot_dialogue, px4_dialogue
from tests.conformance.emulated_target import running_emulator
from tests.conformance.pilot import Pilot
from tests.helpers.sitl_tools import DEFAULT_SETPOINT_TIMEOUT_S

pytestmark = pytest.mark.wallclock

DIALOGUES: dict[Flavour, Callable[[Pilot, Record], None]] = {
    "ardupilot": ardupilot_dialogue, "px4": px4_dialogue}
# May the SITL dialogue fly while the emulator's runs? (conftest.py: PX4 SIH's figures move
# when the machine is busy; ArduCopter's do not.)
FLIES_BESIDE: dict[Flavour, bool] = {"ardupilot": True, "px4": False}
CASES = [pytest.param(flavour, target, id=f"{flavour}-{target}",
                      marks=[pytest.mark.slow] if target == "sitl" else [])
         for flavour in ("ardupilot", "px4") for target in ("emulator", "sitl")]


def _flier(flavour: Flavour, target: str) -> Fly:
    """What flies ``flavour``'s dialogue against ``target`` at a URL, logging to a callable."""

    def fly(url: str, log: Callable[[str], None]) -> None:
        record = Record(f"{flavour} {target}", log=log)
        pilot = Pilot(url, system_id=1, log=log)
        try:
            DIALOGUES[flavour](pilot, record)
        finally:
            pilot.close()
            log(record.table())

    return fly


@pytest.mark.parametrize(("flavour", "target"), CASES)
def test_dialogue(flavour: Flavour, target: str, sitl_flights: SitlFlights) -> None:
    if target == "emulator":
        sitl_flights.start(flavour, _flier(flavour, "sitl"), beside=FLIES_BESIDE[flavour])
        with running_emulator(flavour, DEFAULT_SETPOINT_TIMEOUT_S[flavour]) as url:
            _flier(flavour, target)(url, print)
        return
    sitl_flights.result(flavour, _flier(flavour, target), print)
