"""Fixtures of the conformance suite: SITL boots (and ArduPilot's dialogue) beside the
emulator dialogues.

A SITL autopilot spends its boot waiting on the wall clock (PX4 can arm only ~37 s after it
starts), and a dialogue talks to its own vehicle on its own port. So a flavour's emulator
dialogue (which runs first) starts that flavour's SITL booting, if its SITL dialogue is among
the tests to run (``SitlFlights.start``), and the SITL test then takes the result over
(``SitlFlights.result``). ArduCopter's dialogue also flies in a thread beside the emulator's
(its figures are the same either way); PX4's flies only once the emulator dialogue is over:
SIH's response changes when the machine is busy (beside four busy loops a velocity step
reached 63 % of its speed in 0.62-0.77 s, against 0.51-0.54 s on an idle machine), so PX4's
boot overlaps, its flight does not. Run alone (``-k sitl``), a SITL test boots and flies
itself. At most one SITL instance exists at a time; every instance is stopped when its test
ends (or at the end of the session if its test never ran).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import pytest

from swarm.mavlink.sitl import Kind
from tests.helpers.sitl_tools import BootingSitl, find_firmware, firmware_or_skip

# What flies one dialogue: (companion URL, log) -> None, raising what went wrong.
Fly = Callable[[str, Callable[[str], None]], None]


@dataclass
class Flight:
    """One SITL dialogue flying in a thread: its instance, its log, what it raised."""

    boot: BootingSitl
    lines: list[str] = field(default_factory=list)
    error: BaseException | None = None
    thread: threading.Thread | None = None
    cleared: threading.Event = field(default_factory=threading.Event)  # may fly now

    def run(self, fly: Fly) -> None:
        try:
            url = self.boot.wait().companion_url
            self.cleared.wait()
            fly(url, self.lines.append)
        except BaseException as err:  # handed to the SITL test
            self.error = err


class SitlFlights:
    def __init__(self, session: pytest.Session) -> None:
        self._session = session
        self._flights: dict[Kind, Flight] = {}

    def _selected(self, kind: Kind) -> bool:
        # By name: xdist appends "@<group>" to the node ids of grouped tests.
        return any(item.name.endswith(f"[{kind}-sitl]") for item in self._session.items)

    def start(self, kind: Kind, fly: Fly, *, beside: bool) -> None:
        """Boot ``kind``'s SITL and, in a thread, fly ``fly`` on it once it is ready: at once
        if ``beside``, else once ``result`` asks for it; only if its dialogue will run, its
        firmware is here and no other instance is alive."""
        firmware = find_firmware(kind)
        if self._flights or not self._selected(kind) or firmware is None:
            return
        flight = Flight(BootingSitl(firmware))
        if beside:
            flight.cleared.set()
        self._flights[kind] = flight
        flight.boot.start()
        flight.thread = threading.Thread(target=flight.run, args=(fly,),
                                         name=f"dialogue-{kind}-sitl", daemon=True)
        flight.thread.start()

    def result(self, kind: Kind, fly: Fly, log: Callable[[str], None]) -> None:
        """The SITL dialogue of ``kind``: the flight started earlier, waited for, or one
        flown now (skipped, saying why, without a build); its log goes to ``log``; what it
        raised is raised here. The instance is stopped either way."""
        flight = self._flights.pop(kind, None)
        self.stop_all()
        if flight is None:  # nothing started it: boot and fly here
            flight = Flight(BootingSitl(firmware_or_skip(kind)))
            flight.boot.start()
            flight.cleared.set()
            flight.run(fly)
        else:
            flight.cleared.set()  # PX4's waited for the emulator dialogue to end
        try:
            if flight.thread is not None:
                flight.thread.join()
            for line in flight.lines:
                log(line)
            if flight.error is not None:
                raise flight.error
        finally:
            flight.boot.stop()

    def stop_all(self) -> None:
        while self._flights:
            _, flight = self._flights.popitem()
            flight.boot.stop()  # its dialogue then fails on a closed link and ends
            flight.cleared.set()
            if flight.thread is not None:
                flight.thread.join(timeout=30.0)


@pytest.fixture(scope="session")
def sitl_flights(request: pytest.FixtureRequest) -> Iterator[SitlFlights]:
    flights = SitlFlights(request.session)
    try:
        yield flights
    finally:
        flights.stop_all()
