"""A healthy link to real ArduCopter firmware (SITL) rejects nothing, from the autopilot's
boot to the end action (issue 43, point 7).

ArduPilot's console is also its first MAVLink port (SERIAL0, the agent's link): while it
boots it prints its gyro calibration there ("Init Gyro", a "*" per round, a newline), one
datagram per print between its frames. Every agent listening during the boot counted those
as rejected frames (``bad_data``). The link here is bound before the autopilot starts, so it
hears the whole boot, and then flies the handshake from the ground, a short hover and the
end action as an agent does.

Skipped, saying why, when no SITL build is found (``tests/helpers/sitl_tools.py``).
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import numpy as np
import pytest

from swarm.mavlink.link import AutopilotLink
from swarm.mavlink.sitl import free_udp_port
from tests.helpers.sitl_tools import BOOT_TIMEOUT_S, firmware_or_skip, running_sitl

pytestmark = [pytest.mark.slow, pytest.mark.wallclock]

START_W = np.array([0.0, 0.0, 1.5])  # climbed to from the ground [m]
HOVER_S = 1.0


def test_a_link_listening_from_arducopters_boot_rejects_nothing() -> None:
    firmware = firmware_or_skip("ardupilot")
    port = free_udp_port()
    logs: list[str] = []
    link = AutopilotLink(f"udpin:127.0.0.1:{port}", 0, "ardupilot", np.zeros(3),
                         log=logs.append)  # bound before the autopilot starts
    try:
        with running_sitl(firmware, companion_port=port, wait_ready=False) as sitl:
            # the monitor sets the boot speedup back to 1x once the autopilot is ready
            ready = threading.Thread(target=sitl.monitor.wait_ready, args=(BOOT_TIMEOUT_S,),
                                     daemon=True)
            ready.start()
            link.handshake(timeout_s=BOOT_TIMEOUT_S, start_position_w=START_W)
            end = time.monotonic() + HOVER_S
            stamp = 1
            while time.monotonic() < end:
                link.send_velocity(np.zeros(3), stamp)
                stamp += 20
                link.poll()
                link.wait_readable(0.02)
            assert link.end_mission("hold"), logs
            ready.join(timeout=BOOT_TIMEOUT_S)
    finally:
        link.close()
    assert link.rejections == Counter(), link.rejections
    assert link.rejected_frames == 0
    # the boot's console text was heard (what this test is about), logged as such
    assert link.console_text_bytes > 0, logs
    assert any(line.startswith("drone 0: autopilot console (text on its MAVLink port, not "
                               "MAVLink; not a rejected frame): Init Gyro")
               for line in logs), logs
