"""Fixtures of the conformance suite: SITL boots that can start early.

PX4 SITL can arm only ~37 s after it starts. When a flavour's SITL dialogue is among the
tests to run, its emulator dialogue (which runs first) starts that SITL booting in the
background (``SitlBoots.prestart``), and the SITL dialogue then takes the instance over
(``SitlBoots.take``) — so the boot overlaps the emulator run instead of adding to it. At most
one instance exists at a time: nothing is prestarted while another instance is alive, and
every instance is stopped when its test ends (or at the end of the session if its test never
ran).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from swarm.sitl import Kind
from tests.sitl_tools import BootingSitl, find_firmware, firmware_or_skip


class SitlBoots:
    def __init__(self, session: pytest.Session) -> None:
        self._session = session
        self._boots: dict[Kind, BootingSitl] = {}

    def _selected(self, kind: Kind) -> bool:
        return any(item.nodeid.endswith(f"[{kind}-sitl]") for item in self._session.items)

    def prestart(self, kind: Kind) -> None:
        """Start ``kind``'s SITL booting if its dialogue will run and no other is alive."""
        firmware = find_firmware(kind)
        if self._boots or not self._selected(kind) or firmware is None:
            return
        boot = BootingSitl(firmware)
        self._boots[kind] = boot
        boot.start()

    def take(self, kind: Kind) -> BootingSitl:
        """The prestarted instance of ``kind`` (the caller stops it), else a new one started
        now; any other instance is stopped first."""
        boot = self._boots.pop(kind, None)
        self.stop_all()
        if boot is None:
            boot = BootingSitl(firmware_or_skip(kind))
            boot.start()
        return boot

    def stop_all(self) -> None:
        while self._boots:
            _, boot = self._boots.popitem()
            boot.stop()


@pytest.fixture(scope="session")
def sitl_boots(request: pytest.FixtureRequest) -> Iterator[SitlBoots]:
    boots = SitlBoots(request.session)
    try:
        yield boots
    finally:
        boots.stop_all()
