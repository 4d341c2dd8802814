"""One MAVLink dialogue per flavour, against the real autopilot and against our emulator.

``tests/conformance/dialogue.py`` holds the dialogues (what is sent, what must come back,
and the bands of what is measured); this runs each against

* ``sitl``: the real firmware in SITL (ArduCopter, PX4 with SIH; ``tests/sitl_tools.py``), found
  through ``VIGIL_ARDUCOPTER`` / ``VIGIL_PX4`` or in ``../shared/autopilots``; skipped, saying
  why, when absent; marked slow;
* ``emulator``: ``sim_world``'s ``EmulatedVehicle`` in a ``VehicleFleet`` of one on real UDP
  (``emulated_target``), starting on the ground with the flavour's measured velocity
  response.

Both must give the same answers and land in the same bands. Run with ``-s`` to see the
conversation and each figure. Wall time per flavour, both targets: ArduCopter ~100 s,
PX4 ~110 s (its ~37 s boot overlaps the emulator's run, see ``conftest.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from sim_world.vehicle import Flavour
from tests.conformance.conftest import SitlBoots
from tests.conformance.dialogue import Record, ardupilot_dialogue, px4_dialogue
from tests.conformance.emulated_target import running_emulator
from tests.conformance.pilot import Pilot
from tests.sitl_tools import DEFAULT_SETPOINT_TIMEOUT_S

DIALOGUES: dict[Flavour, Callable[[Pilot, Record], None]] = {
    "ardupilot": ardupilot_dialogue, "px4": px4_dialogue}
CASES = [pytest.param(flavour, target, id=f"{flavour}-{target}",
                      marks=[pytest.mark.slow] if target == "sitl" else [])
         for flavour in ("ardupilot", "px4") for target in ("emulator", "sitl")]


def _fly(flavour: Flavour, target: str, url: str) -> None:
    record = Record(f"{flavour} {target}", log=print)
    pilot = Pilot(url, system_id=1, log=print)
    try:
        DIALOGUES[flavour](pilot, record)
    finally:
        pilot.close()
        print(record.table())


@pytest.mark.parametrize(("flavour", "target"), CASES)
def test_dialogue(flavour: Flavour, target: str, sitl_boots: SitlBoots) -> None:
    if target == "emulator":
        sitl_boots.prestart(flavour)
        with running_emulator(flavour, DEFAULT_SETPOINT_TIMEOUT_S[flavour]) as url:
            _fly(flavour, target, url)
        return
    boot = sitl_boots.take(flavour)  # skips, saying why, when there is no build
    try:
        _fly(flavour, target, boot.wait().companion_url)
    finally:
        boot.stop()
