"""The key space of a run: every Zenoh key expression under ``vigil/<run_id>/``; different
run ids never match."""

from __future__ import annotations

import re
from typing import Any, Final

KEY_ROOT: Final = "vigil"

_RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


# -- key expressions -----------------------------------------------------------------------------


def _index(name: str, i: Any) -> int:
    if isinstance(i, bool) or not isinstance(i, int) or i < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {i!r}")
    return i


class Keys:
    """Key expressions of one run, all under ``vigil/<run_id>/``."""

    def __init__(self, run_id: str) -> None:
        if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
            raise ValueError("run_id must be 1-64 characters of [A-Za-z0-9_-], got "
                             f"{run_id!r:.80}")
        self.run_id = run_id
        self.prefix = f"{KEY_ROOT}/{run_id}"
        self.truth = f"{self.prefix}/world/truth"
        self.clock = f"{self.prefix}/world/clock"
        # Every drone's beacon, relayed by the world (lockstep: step k's; realtime: the newest).
        self.beacon_relay = f"{self.prefix}/world/beacons"
        self.all_consensus = f"{self.prefix}/agent/*/consensus"
        self.all_beacons = f"{self.prefix}/agent/*/beacon"
        self.all_telemetry = f"{self.prefix}/agent/*/telemetry"
        self.all_cameras = f"{self.prefix}/world/camera/*"
        self.all_images = f"{self.prefix}/world/image/*"
        self.everything = f"{self.prefix}/**"
        self._source = re.compile(
            rf"^{re.escape(self.prefix)}/(?:agent/(\d{{1,9}})/(?:consensus|beacon|telemetry)"
            rf"|world/(?:camera|image)/(\d{{1,9}}))$")

    def consensus(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/consensus"

    def beacon(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/beacon"

    def telemetry(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/telemetry"

    def camera(self, i: int) -> str:
        return f"{self.prefix}/world/camera/{_index('drone id', i)}"

    def image(self, i: int) -> str:
        """A rendered camera's images (camera.model = "rendered"), read by drone i's
        detector, which publishes the frames on ``camera(i)``."""
        return f"{self.prefix}/world/image/{_index('drone id', i)}"

    def source_id(self, key: str) -> int | None:
        """The drone id in an agent, camera or image key of this run (None for other keys).

        A subscriber on a wildcard can check it against the id inside the payload.
        """
        match = self._source.match(str(key))
        if match is None:
            return None
        return int(match.group(1) or match.group(2))

    def __repr__(self) -> str:
        return f"Keys({self.run_id!r})"
