"""sim_world.fleet.VehicleFleet on real UDP: whom each vehicle's stream goes to."""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Callable

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.fleet import VehicleFleet
from swarm.models.kinematics import VelocityResponse
from tests.helpers.vehicle_tools import Agent


def _one(sock: socket.socket, timeout: float = 2.0) -> bytes | None:
    return sock.recv(65535) if select.select([sock], [], [], timeout)[0] else None


def _drain(sock: socket.socket) -> None:
    while select.select([sock], [], [], 0.05)[0]:
        sock.recv(65535)


def _service_until(fleet: VehicleFleet, condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + 5.0
    while not condition():
        assert time.monotonic() < deadline, "the fleet never got there"
        fleet.service(0.1)


def test_mavlink_like_junk_never_takes_the_stream_away_from_the_agent() -> None:
    """Junk starting with the MAVLink 2 magic used to make the vehicle send its telemetry to
    the junk's sender (the agent then waited for positions that never came). Only a sender
    whose frame the vehicle took (a relay such as MAVProxy) is followed."""
    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    junk.bind(("127.0.0.1", 0))
    relay = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    relay.bind(("127.0.0.1", 0))
    clock = [10.0]
    fleet = VehicleFleet(np.array([[0.0, 0.0, 3.0]]), [np.zeros(3)], "px4", host="127.0.0.1",
                         base_port=agent.getsockname()[1], u_max_m_s=3.0,
                         setpoint_timeout_s=0.5, clock=lambda: clock[0])
    vehicle, endpoint = fleet.vehicles[0], fleet.endpoints[0]
    try:
        # sent by a stranger: junk, a bad-CRC frame, a NaN setpoint with a valid CRC
        bad_crc = bytearray(Agent(target=1).arm())
        bad_crc[-1] ^= 0xFF
        nan_setpoint = Agent(target=1).setpoint([np.nan, 0.0, 0.0], stamp=5)
        gcs = Agent(sysid=255, compid=190)
        heartbeat = gcs.pack(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0))  # valid, but ignored
        for datagram in (b"\xfd\x09junk-junk", bytes(bad_crc), nan_setpoint, b"", heartbeat):
            junk.sendto(datagram, endpoint.local_address)
        _service_until(fleet, lambda: vehicle.rejected_frames >= 4
                       and vehicle.ignored_messages >= 1)
        assert vehicle.accepted_frames == 0
        assert endpoint.peer_address == agent.getsockname()
        _drain(agent)
        fleet.send_telemetry(20)
        assert _one(agent) is not None  # the agent still gets its positions
        assert _one(junk, 0.1) is None
        # a relay whose frame the vehicle takes is followed, as PX4 SITL follows MAVProxy
        relay.sendto(Agent(target=1).arm(), endpoint.local_address)
        _service_until(fleet, lambda: vehicle.accepted_frames >= 1)
        assert endpoint.peer_address == relay.getsockname()
        reply = _one(relay)
        assert reply is not None and mav.MAVLink(None).parse_buffer(reply)[0].get_type() \
            == "COMMAND_ACK"
    finally:
        fleet.close()
        for sock in (agent, junk, relay):
            sock.close()


def test_fleet_vehicles_take_start_and_response_and_fly_themselves() -> None:
    """``start`` and ``response`` reach every vehicle; ``fly`` lets each vehicle fly its own
    mode (here one takes off from the ground, the other stays there) on the fleet's clock."""
    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    clock = [1.0]
    response = VelocityResponse(time_constant_s=0.5, accel_limit_m_s2=2.0)
    fleet = VehicleFleet(np.array([[0.0, 0.0, 3.0], [5.0, 0.0, 3.0]]), [np.zeros(3)] * 2,
                         "ardupilot", host="127.0.0.1", base_port=agent.getsockname()[1],
                         u_max_m_s=3.0, setpoint_timeout_s=3.0, clock=lambda: clock[0],
                         start="ground", response=response)
    try:
        np.testing.assert_array_equal(fleet.positions_w, [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
        for vehicle in fleet.vehicles:
            assert vehicle.response is response and not vehicle.armed
            assert vehicle.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
        second = Agent(target=2)
        for message in (second.set_mode(4), second.arm(),
                        second.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0)):
            assert fleet.vehicles[1].receive(message, clock[0])
        for _ in range(600):
            clock[0] += 0.02
            fleet.fly(0.02)
        positions = fleet.positions_w
        assert positions[0][2] == 0.0 and not fleet.vehicles[0].armed
        assert positions[1][2] == pytest.approx(2.0, abs=0.1)
        assert fleet.vehicles[1].landed_state == mav.MAV_LANDED_STATE_IN_AIR
    finally:
        fleet.close()
        agent.close()


def test_service_names_the_vehicles_whose_links_had_datagrams() -> None:
    """A lockstep world looks for the step's setpoint only at the vehicles ``service`` names
    (O(N) a step, not O(N) per wake-up): every vehicle a datagram came to, none other."""
    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    fleet = VehicleFleet(np.array([[0.0, 0.0, 3.0], [2.0, 0.0, 3.0], [4.0, 0.0, 3.0]]),
                         [np.zeros(3)] * 3, "px4", host="127.0.0.1",
                         base_port=agent.getsockname()[1], u_max_m_s=3.0,
                         setpoint_timeout_s=0.5, clock=lambda: 10.0)
    try:
        assert fleet.service(0.0) == []
        for i in (2, 0):
            agent.sendto(Agent(target=i + 1).setpoint([0.5, 0.0, 0.0], stamp=40),
                         fleet.endpoints[i].local_address)
        served: list[int] = []
        deadline = time.monotonic() + 5.0
        while sorted(served) != [0, 2]:
            assert time.monotonic() < deadline, served
            served += fleet.service(0.1)
        assert [v.accepted_frames for v in fleet.vehicles] == [1, 0, 1]
        assert fleet.service(0.0) == []
    finally:
        fleet.close()
        agent.close()
