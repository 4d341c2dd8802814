"""Our emulated vehicle as a conformance target: a ``VehicleFleet`` of one, on real UDP.

``running_emulator(flavour, setpoint_timeout_s)`` is a context manager: one vehicle (system
id 1) starting on the ground (``start="ground"``) with the firmware's measured velocity
response (``MEASURED_RESPONSE``), served by ``sim_world.fleet.serve_forever`` at 50 Hz on
the wall clock in a thread of its own; it sends its companion link to a free UDP port on
127.0.0.1 and yields that port's pymavlink ``udpin`` URL, as
``tests.helpers.sitl_tools.running_sitl``
does for a real autopilot. The thread and the sockets are stopped and closed on the way out.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np

from sim_world.fleet import VehicleFleet, serve_forever
from sim_world.vehicle import MEASURED_RESPONSE, Flavour
from swarm.mavlink.sitl import free_udp_port

TICK_S = 0.02  # 50 Hz, as sim-world and sim-vehicles run
ORIGIN_W = np.array([0.0, 0.0, 0.0])


@contextlib.contextmanager
def running_emulator(flavour: Flavour, setpoint_timeout_s: float) -> Iterator[str]:
    port = free_udp_port()
    started = time.monotonic()
    fleet = VehicleFleet(np.array([[0.0, 0.0, 0.0]]), [ORIGIN_W], flavour, host="127.0.0.1",
                         base_port=port, u_max_m_s=3.0, setpoint_timeout_s=setpoint_timeout_s,
                         clock=lambda: time.monotonic() - started, start="ground",
                         response=MEASURED_RESPONSE[flavour])
    stop = threading.Event()
    thread = threading.Thread(target=serve_forever, args=(fleet, TICK_S, started, stop.is_set),
                              name=f"emulated-{flavour}", daemon=True)
    thread.start()
    try:
        yield f"udpin:127.0.0.1:{port}"
    finally:
        stop.set()
        thread.join(timeout=5.0)
        fleet.close()
