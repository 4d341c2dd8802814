"""Fixtures of the conformance suite: SITL dialogues that run beside the emulator's.

The dialogues talk to different vehicles on different ports and spend their time waiting on
the wall clock (a velocity step takes seconds to settle, PX4 can arm only ~37 s after it
starts; the whole suite uses a fraction of a core). So the first emulator dialogue starts
every SITL whose dialogue is among the tests to run booting and, once each is ready, flies its
dialogue in a thread of its own (``SitlFlights.start``) while the emulator dialogues run in
the tests; each SITL test then waits for its flight and reports its result and conversation
(``SitlFlights.result``). Run alone (``-k sitl``), a SITL test flies its dialogue itself.
At most one SITL instance per flavour exists at a time, and every instance is stopped when
its test ends (or at the end of the session if its test never ran).
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

    def run(self, fly: Fly) -> None:
        try:
            fly(self.boot.wait().companion_url, self.lines.append)
        except BaseException as err:  # handed to the SITL test
            self.error = err


class SitlFlights:
    def __init__(self, session: pytest.Session) -> None:
        self._session = session
        self._flights: dict[Kind, Flight] = {}

    def _selected(self, kind: Kind) -> bool:
        return any(item.nodeid.endswith(f"[{kind}-sitl]") for item in self._session.items)

    def start(self, kind: Kind, fly: Fly) -> None:
        """Boot ``kind``'s SITL and fly ``fly`` on it in a thread, if its dialogue will run,
        its firmware is here and it is not flying yet."""
        firmware = find_firmware(kind)
        if kind in self._flights or not self._selected(kind) or firmware is None:
            return
        flight = Flight(BootingSitl(firmware))
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
        if flight is None:
            flight = Flight(BootingSitl(firmware_or_skip(kind)))
            flight.boot.start()
            flight.run(fly)
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
            if flight.thread is not None:
                flight.thread.join(timeout=30.0)


@pytest.fixture(scope="session")
def sitl_flights(request: pytest.FixtureRequest) -> Iterator[SitlFlights]:
    flights = SitlFlights(request.session)
    try:
        yield flights
    finally:
        flights.stop_all()
