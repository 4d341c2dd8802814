"""A fleet of emulated MAVLink vehicles, each on its own UDP endpoint (SPEC §12).

Used by the world process, and standalone by ``sim-vehicles``: N PX4/ArduPilot-style
autopilots flying at 50 Hz, a stand-in for N SITL instances when the world runs with
``--vehicles external``.
"""

from __future__ import annotations

import selectors
import time
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle, Flavour

HEARTBEAT_PERIOD_S = 1.0

Array = NDArray[np.float64]


class VehicleFleet:
    """Vehicles i = 0..N−1; vehicle i sends to (host, base + i) and answers whoever talks."""

    def __init__(self, positions_w: Array, origins_w: Sequence[Array], flavour: Flavour, *,
                 host: str, base_port: int, u_max_m_s: float, setpoint_timeout_s: float,
                 clock: Callable[[], float]) -> None:
        self.clock = clock  # the fleet's notion of "now" [s] (wall, or a lockstep sim clock)
        self.vehicles: list[EmulatedVehicle] = []
        self.endpoints: list[VehicleEndpoint] = []
        self.selector = selectors.DefaultSelector()
        self._last_heartbeat = -np.inf
        try:
            for i, position in enumerate(positions_w):
                self.vehicles.append(EmulatedVehicle(
                    i, flavour, position, origins_w[i], u_max_m_s=u_max_m_s,
                    setpoint_timeout_s=setpoint_timeout_s))
                endpoint = VehicleEndpoint((host, base_port + i))
                self.endpoints.append(endpoint)
                self.selector.register(endpoint.fileno(), selectors.EVENT_READ, i)
        except OSError:
            self.close()
            raise

    def __len__(self) -> int:
        return len(self.vehicles)

    @property
    def positions_w(self) -> Array:
        return np.array([v.position_w for v in self.vehicles])

    def service(self, timeout_s: float) -> None:
        """Handle every datagram that arrives within ``timeout_s``; heartbeats at 1 Hz."""
        now = self.clock()
        if now - self._last_heartbeat >= HEARTBEAT_PERIOD_S:
            self._last_heartbeat = now
            for vehicle, endpoint in zip(self.vehicles, self.endpoints, strict=True):
                endpoint.send([vehicle.heartbeat()])
        for key, _ in self.selector.select(timeout=max(timeout_s, 0.0)):
            i = key.data
            for chunk in self.endpoints[i].poll():
                replies = self.vehicles[i].receive(chunk, self.clock())
                if replies:
                    self.endpoints[i].send(replies)

    def send_telemetry(self, time_boot_ms: int) -> None:
        now = self.clock()
        for vehicle, endpoint in zip(self.vehicles, self.endpoints, strict=True):
            endpoint.send(vehicle.telemetry(time_boot_ms, now))

    def fly(self, dt_s: float) -> None:
        """Move every vehicle for dt with what it applies now (setpoint, hold or nothing)."""
        now = self.clock()
        for vehicle in self.vehicles:
            vehicle.integrate(dt_s, vehicle.commanded_velocity_w(now))

    def rejected_frames(self) -> int:
        return sum(v.rejected_frames for v in self.vehicles)

    def close(self) -> None:
        for endpoint in self.endpoints:
            endpoint.close()
        self.selector.close()


def serve_forever(fleet: VehicleFleet, dt_s: float, started: float,
                  stop: Callable[[], bool] = lambda: False) -> None:
    """Realtime loop of a standalone fleet: telemetry, commands and motion every dt."""
    next_tick = time.monotonic()
    while not stop():
        fleet.send_telemetry(int((time.monotonic() - started) * 1000))
        next_tick += dt_s
        while (remaining := next_tick - time.monotonic()) > 0:
            fleet.service(remaining)
        if -remaining > dt_s:  # fell behind (machine stalled): resynchronize, don't burst
            next_tick = time.monotonic()
        fleet.fly(dt_s)
