"""A fleet of emulated MAVLink vehicles, each on its own UDP endpoint (SPEC §12).

Used by the world process, and standalone by ``sim-vehicles``: N PX4/ArduPilot-style
autopilots flying at 50 Hz, a stand-in for N SITL instances when the world runs with
``--vehicles external``.

With a MAVLink signing key every vehicle signs and checks signatures, and its endpoint
follows a new sender only once one of its frames passed the signature check: an unsigned or
forged datagram is dropped unanswered and cannot redirect the vehicle's telemetry. Without
signing the endpoint follows a new sender (a relay such as MAVProxy) only once the vehicle
took one of its frames (valid checksum, a message it handles, sane values): junk that merely
starts like MAVLink (0xFD) is counted and dropped and never takes the stream away from the
agent, and neither does a valid frame it ignores (another GCS's heartbeat).

With a ground station (``gcs=(host, port)``) every vehicle also has a ground-station link
(``sim_world.gcs_link``): its own UDP socket sending to that one address, as every PX4 SITL
instance sends to 14550, so one ground station (``mavproxy.py --master udpin:HOST:PORT``,
QGroundControl) sees the whole fleet, one system id per vehicle. It may only watch unless
``gcs_control``; what it asks and is refused is logged through ``log``.

Public API: ``VehicleFleet(positions_w, origins_w, flavour, *, host, base_port, u_max_m_s,
setpoint_timeout_s, clock, signing_key=None, start="air", response=VelocityResponse(),
gcs=None, gcs_control=False, geo_origin=GeoPoint(*DEFAULT_GEO_ORIGIN), log=None)``
(``start`` and ``response`` as ``EmulatedVehicle`` takes them, the same for every vehicle)
with ``service(timeout_s)``, ``send_telemetry(time_boot_ms)``, ``fly(dt_s)`` (every vehicle
flies itself: ``EmulatedVehicle.fly``), ``positions_w``, ``rejected_frames()``,
``gcs_links``, ``close()``; ``serve_forever(fleet, dt_s, started, stop)``;
``mavlink_hosts``, ``bind_address_for``.
"""

from __future__ import annotations

import ipaddress
import selectors
import time
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from sim_world.gcs_link import GcsLink
from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle, Flavour, Start
from swarm.errors import UsageError
from swarm.models.frames import GeoPoint
from swarm.models.kinematics import VelocityResponse
from swarm.scenario.config import DEFAULT_GEO_ORIGIN

HEARTBEAT_PERIOD_S = 1.0

Array = NDArray[np.float64]


class MavlinkHostsError(UsageError, ValueError):
    """A ``--mavlink-host`` that names neither one address nor one per drone."""


def mavlink_hosts(host: str, n: int) -> list[str]:
    """``--mavlink-host``: where each vehicle sends, i.e. where its agent listens. One address
    for every vehicle, or N comma-separated addresses, vehicle 0 first (agents spread over
    several machines). MavlinkHostsError (one line) otherwise."""
    hosts = [part.strip() for part in host.split(",")]
    if not all(hosts) or len(hosts) not in (1, n):
        raise MavlinkHostsError(f"--mavlink-host {host!r}: give one address for every drone "
                                f"or {n} comma-separated addresses, one per drone")
    return hosts * n if len(hosts) == 1 else hosts


def bind_address_for(host: str) -> tuple[str, int]:
    """The vehicle's own socket: on loopback when its agent is on this machine, else on every
    interface (a socket bound to 127.0.0.1 cannot send off the machine: EINVAL)."""
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name
        loopback = host == "localhost"
    return ("127.0.0.1", 0) if loopback else ("0.0.0.0", 0)


class VehicleFleet:
    """Vehicles i = 0..N−1; vehicle i sends to (host_i, base + i) and answers whoever talks
    (``host``: one address, or one per vehicle comma-separated, see ``mavlink_hosts``)."""

    def __init__(self, positions_w: Array, origins_w: Sequence[Array], flavour: Flavour, *,
                 host: str, base_port: int, u_max_m_s: float, setpoint_timeout_s: float,
                 clock: Callable[[], float], signing_key: bytes | None = None,
                 start: Start = "air",
                 response: VelocityResponse = VelocityResponse(),  # noqa: B008
                 gcs: tuple[str, int] | None = None, gcs_control: bool = False,
                 geo_origin: GeoPoint = GeoPoint(*DEFAULT_GEO_ORIGIN),  # noqa: B008
                 log: Callable[[str], None] | None = None) -> None:
        self.clock = clock  # the fleet's notion of "now" [s] (wall, or a lockstep sim clock)
        # ``clock`` is the wall clock: each frame is handled at its datagram's arrival time,
        # so a stall of the serving loop never fails a vehicle safe whose setpoints came in
        # time. Off while ``clock`` is a lockstep sim clock, where waiting is not time.
        self.arrival_times = True
        self.vehicles: list[EmulatedVehicle] = []
        self.endpoints: list[VehicleEndpoint] = []
        self.selector = selectors.DefaultSelector()
        self._last_heartbeat = -np.inf
        self.gcs_links: list[GcsLink] = []
        self.gcs_endpoints: list[VehicleEndpoint] = []
        hosts = mavlink_hosts(host, len(positions_w))
        try:
            for i, position in enumerate(positions_w):
                self.vehicles.append(EmulatedVehicle(
                    i, flavour, position, origins_w[i], u_max_m_s=u_max_m_s,
                    setpoint_timeout_s=setpoint_timeout_s, signing_key=signing_key,
                    start=start, response=response))
                endpoint = VehicleEndpoint((hosts[i], base_port + i),
                                           bind_address=bind_address_for(hosts[i]),
                                           follow_sender=False)  # service() decides
                self.endpoints.append(endpoint)
                self.selector.register(endpoint.fileno(), selectors.EVENT_READ, i)
                if gcs is not None:
                    self.gcs_links.append(GcsLink(self.vehicles[i], geo_origin,
                                                  control=gcs_control, log=log))
                    gcs_endpoint = VehicleEndpoint(gcs, bind_address=bind_address_for(gcs[0]),
                                                   follow_sender=False)
                    self.gcs_endpoints.append(gcs_endpoint)
                    self.selector.register(gcs_endpoint.fileno(), selectors.EVENT_READ,
                                           -1 - i)
        except (OSError, ValueError):
            self.close()
            raise

    def __len__(self) -> int:
        return len(self.vehicles)

    @property
    def positions_w(self) -> Array:
        return np.array([v.position_w for v in self.vehicles])

    def reported_positions_w(self) -> Array:
        """(N, 3): each vehicle's position as its agent reads it from LOCAL_POSITION_NED."""
        return np.array([v.reported_position_w for v in self.vehicles])

    def service(self, timeout_s: float) -> list[int]:
        """Handle every datagram that arrives within ``timeout_s``; heartbeats at 1 Hz.
        Returns the vehicles whose links (agent or ground station) had datagrams: only their
        state can have changed (a lockstep world looks at those for the step's setpoint)."""
        now = self.clock()
        if now - self._last_heartbeat >= HEARTBEAT_PERIOD_S:
            self._last_heartbeat = now
            for vehicle, endpoint in zip(self.vehicles, self.endpoints, strict=True):
                endpoint.send([vehicle.heartbeat()])
        served: list[int] = []
        for key, _ in self.selector.select(timeout=max(timeout_s, 0.0)):
            i = key.data
            if i < 0:  # a vehicle's ground-station link (-1 - vehicle index)
                self._service_gcs(-1 - i)
                served.append(-1 - i)
                continue
            served.append(i)
            vehicle, endpoint = self.vehicles[i], self.endpoints[i]
            for chunk, sender, age in endpoint.poll_from():
                taken = vehicle.authenticated_frames if vehicle.signing \
                    else vehicle.accepted_frames
                replies = vehicle.receive(chunk, self.clock() - (age if self.arrival_times
                                                                 else 0.0))
                # Replies go to whoever holds the key (signing), else to whoever sent a frame
                # the vehicle took: junk, however MAVLink-like, never redirects the stream.
                if (vehicle.authenticated_frames if vehicle.signing
                        else vehicle.accepted_frames) > taken:
                    endpoint.follow(sender)
                if replies:
                    endpoint.send(replies)
        return served

    def _service_gcs(self, i: int) -> None:
        link, endpoint = self.gcs_links[i], self.gcs_endpoints[i]
        # Answers go to the ground station's address, as the streams do (a GCS listening on
        # a port also sends from it); another sender never takes the link over.
        for chunk, _sender, _age in endpoint.poll_from():
            replies = link.receive(chunk, self.clock())
            if replies:
                endpoint.send(replies)

    def send_telemetry(self, time_boot_ms: int) -> None:
        now = self.clock()
        for vehicle, endpoint in zip(self.vehicles, self.endpoints, strict=True):
            endpoint.send(vehicle.telemetry(time_boot_ms, now))
        for link, endpoint in zip(self.gcs_links, self.gcs_endpoints, strict=True):
            endpoint.send(link.telemetry(time_boot_ms, now))

    def fly(self, dt_s: float) -> None:
        """Every vehicle flies itself for dt up to now (``EmulatedVehicle.fly``: its mode's
        guidance — setpoints, takeoff, hold, land, return —, its response, the ground)."""
        now = self.clock()
        for vehicle in self.vehicles:
            vehicle.fly(dt_s, now)

    def rejected_frames(self) -> int:
        return sum(v.rejected_frames for v in self.vehicles)

    def close(self) -> None:
        for endpoint in [*self.endpoints, *self.gcs_endpoints]:
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
