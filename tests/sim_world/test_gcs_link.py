"""sim_world.gcs_link: a ground station's link to an emulated vehicle (issue 17, point 4).

In process: the streams and their rates, where GLOBAL_POSITION_INT puts the vehicle on Earth
(checked with tests/helpers/geo_tools.haversine_m, not the code under test), and the rule that a
ground station watches but cannot fly the vehicle unless it is allowed to. On real UDP: a
fleet's ground-station links all reach one GCS socket, one system id per vehicle.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.fleet import VehicleFleet, serve_forever
from sim_world.gcs_link import GCS_STREAM_PERIODS_S, GcsLink
from sim_world.vehicle import EmulatedVehicle, Flavour
from swarm.models.frames import GeoPoint
from tests.helpers.geo_tools import haversine_m

ORIGIN = GeoPoint(-35.363261, 149.165230, 584.0)
GCS_SYSTEM = 255


class Gcs:
    """A ground station's encoder and decoder (system 255, MAV_COMP_ID_MISSIONPLANNER)."""

    def __init__(self) -> None:
        self.out = mav.MAVLink(None, srcSystem=GCS_SYSTEM, srcComponent=190)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True

    def frame(self, msg) -> bytes:
        return msg.pack(self.out)

    def decode(self, packets: list[bytes]) -> list:
        return [m for p in packets for m in (self.parser.parse_buffer(p) or [])]


def _vehicle(flavour: Flavour = "px4", start: str = "air", **kwargs) -> EmulatedVehicle:
    return EmulatedVehicle(1, flavour, np.array([30.0, -40.0, 5.0]), np.array([0.0, 0.0, 0.0]),
                           start=start, **kwargs)


def test_streams_at_their_rates_and_puts_the_vehicle_where_it_is_on_earth() -> None:
    vehicle = _vehicle()
    link, gcs = GcsLink(vehicle, ORIGIN), Gcs()
    counts: Counter[str] = Counter()
    last = {}
    for k in range(100):  # 2 s at 50 Hz
        for msg in gcs.decode(link.telemetry(1000 + 20 * k, 20.0 + 0.02 * k)):
            counts[msg.get_type()] += 1
            last[msg.get_type()] = msg
            assert msg.get_srcSystem() == vehicle.system_id
    expected = {name: round(2.0 / period) for name, period in GCS_STREAM_PERIODS_S.items()}
    assert counts == expected
    assert last["HEARTBEAT"].autopilot == mav.MAV_AUTOPILOT_PX4
    assert last["HEARTBEAT"].base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED  # started in the air
    gpi = last["GLOBAL_POSITION_INT"]
    # 30 m east, 40 m south, 5 m up of the world origin (= this vehicle's home).
    lat, lon = gpi.lat * 1e-7, gpi.lon * 1e-7
    assert haversine_m(ORIGIN.lat_deg, ORIGIN.lon_deg, lat, lon) == pytest.approx(50.0, abs=0.02)
    assert haversine_m(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.lat_deg, lon) == pytest.approx(
        30.0, abs=0.02)
    assert lat < ORIGIN.lat_deg and lon > ORIGIN.lon_deg  # south-east
    assert gpi.relative_alt == 5000 and gpi.alt == round((ORIGIN.alt_m + 5.0) * 1000)
    assert gpi.hdg == 0xFFFF
    lpn = last["LOCAL_POSITION_NED"]
    assert (lpn.x, lpn.y, lpn.z) == pytest.approx((-40.0, 30.0, -5.0))


def test_a_ground_station_cannot_arm_switch_or_move_the_vehicle() -> None:
    said: list[str] = []
    vehicle = _vehicle("ardupilot", start="ground")
    link, gcs = GcsLink(vehicle, ORIGIN, log=said.append), Gcs()
    before = (vehicle.armed, vehicle.mode, dict(vehicle.params))
    arm = gcs.out.command_long_encode(vehicle.system_id, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM,
                                      0, 1, 0, 0, 0, 0, 0, 0)
    replies = gcs.decode(link.receive(gcs.frame(arm), 1.0) + link.receive(gcs.frame(arm), 1.1))
    acks = [m for m in replies if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(400, mav.MAV_RESULT_DENIED)] * 2
    assert any(m.get_type() == "STATUSTEXT" and "read-only" in m.text for m in replies)
    guided = gcs.out.set_mode_encode(vehicle.system_id, 1, 4)
    setpoint = gcs.out.set_position_target_local_ned_encode(
        0, vehicle.system_id, 1, mav.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, 1.0, 0, 0,
        0, 0, 0, 0, 0)
    name = next(iter(vehicle.params))
    param_set = gcs.out.param_set_encode(vehicle.system_id, 1, name.encode(), 1e6,
                                         mav.MAV_PARAM_TYPE_REAL32)
    upload = gcs.out.mission_count_encode(vehicle.system_id, 1, 3, 0)
    replies = gcs.decode([p for m in (guided, setpoint, param_set, upload)
                          for p in link.receive(gcs.frame(m), 1.2)])
    assert {m.get_type() for m in replies} == {"PARAM_VALUE", "MISSION_ACK"}
    value = next(m for m in replies if m.get_type() == "PARAM_VALUE")
    assert value.param_id == name and value.param_value == pytest.approx(before[2][name])
    assert next(m for m in replies if m.get_type() == "MISSION_ACK").type == \
        mav.MAV_MISSION_DENIED
    vehicle.fly(0.5, 1.5)
    assert (vehicle.armed, vehicle.mode, dict(vehicle.params)) == before
    assert link.refused == Counter({"COMMAND_LONG 400": 2, "SET_MODE": 1,
                                    "SET_POSITION_TARGET_LOCAL_NED": 1, "PARAM_SET": 1,
                                    "MISSION_COUNT": 1})
    assert len(said) == 5 and all("refused" in line for line in said)  # each kind once
    # Reading is answered, by the vehicle itself.
    listing = gcs.out.param_request_list_encode(vehicle.system_id, 1)
    values = [m for m in gcs.decode(link.receive(gcs.frame(listing), 1.6))
              if m.get_type() == "PARAM_VALUE"]
    assert {m.param_id for m in values} == set(vehicle.params)
    # Another vehicle's command is not this one's to answer.
    other = gcs.out.command_long_encode(vehicle.system_id + 1, 1,
                                        mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert link.receive(gcs.frame(other), 1.7) == []


def test_with_control_the_ground_station_flies_it_and_each_command_is_logged() -> None:
    said: list[str] = []
    vehicle = _vehicle("px4", start="ground")
    link, gcs = GcsLink(vehicle, ORIGIN, control=True, log=said.append), Gcs()
    arm = gcs.out.command_long_encode(vehicle.system_id, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM,
                                      0, 1, 0, 0, 0, 0, 0, 0)
    acks = [m for m in gcs.decode(link.receive(gcs.frame(arm), 1.0))
            if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(400, mav.MAV_RESULT_ACCEPTED)]
    assert vehicle.armed and not link.refused
    assert said == ["drone 1: ground station sent COMMAND_LONG 400"]


def test_a_signing_vehicle_keeps_its_ground_station_link_to_streaming() -> None:
    key = bytes(range(32))
    vehicle = _vehicle(signing_key=key)
    with pytest.raises(ValueError, match="holds no key"):
        GcsLink(vehicle, ORIGIN, control=True)
    link, gcs = GcsLink(vehicle, ORIGIN), Gcs()
    listing = gcs.out.param_request_list_encode(vehicle.system_id, 1)
    assert link.receive(gcs.frame(listing), 1.0) == []
    assert link.refused == Counter({"signed_vehicle": 1})
    assert vehicle.rejected_frames == 0  # never reached the vehicle
    assert any(m.get_type() == "HEARTBEAT" for m in gcs.decode(link.telemetry(0, 0.0)))


def test_junk_from_the_ground_station_is_counted_not_raised() -> None:
    link = GcsLink(_vehicle(), ORIGIN)
    assert link.receive(b"\xfd\x09garbage-not-mavlink" * 3, 1.0) == []
    assert link.receive(b"", 1.0) == []
    assert sum(link.rejections.values()) >= 1 and not link.refused


# ----------------------------------------------------------------------------- real UDP
@pytest.fixture
def served_fleet() -> Iterator[tuple[VehicleFleet, socket.socket, list[str]]]:
    """Three px4 vehicles served at 50 Hz on the wall clock, their ground-station links sending
    to a socket of this test."""
    gcs_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs_socket.bind(("127.0.0.1", 0))
    agents = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # nobody reads: no agents
    agents.bind(("127.0.0.1", 0))
    said: list[str] = []
    started = time.monotonic()
    positions = np.array([[0.0, 0.0, 3.0], [4.0, 0.0, 3.0], [0.0, 4.0, 3.0]])
    fleet = VehicleFleet(positions, [np.zeros(3)] * 3, "px4", host="127.0.0.1",
                         base_port=agents.getsockname()[1], u_max_m_s=3.0,
                         setpoint_timeout_s=1.0, clock=lambda: time.monotonic() - started,
                         gcs=gcs_socket.getsockname(), geo_origin=ORIGIN, log=said.append)
    stop = threading.Event()
    thread = threading.Thread(target=serve_forever, args=(fleet, 0.02, started, stop.is_set),
                              daemon=True)
    thread.start()
    try:
        yield fleet, gcs_socket, said
    finally:
        stop.set()
        thread.join(timeout=5.0)
        fleet.close()
        gcs_socket.close()
        agents.close()


def test_one_ground_station_socket_sees_every_vehicle_and_cannot_arm_any(served_fleet) -> None:
    fleet, gcs_socket, said = served_fleet
    gcs = Gcs()
    senders: dict[int, tuple[str, int]] = {}
    positions: dict[int, object] = {}
    counts: Counter[tuple[int, str]] = Counter()
    start = time.monotonic()
    while time.monotonic() - start < 2.0:
        if select.select([gcs_socket], [], [], 0.1)[0]:
            data, sender = gcs_socket.recvfrom(65535)
            for msg in gcs.decode([data]):
                counts[(msg.get_srcSystem(), msg.get_type())] += 1
                senders[msg.get_srcSystem()] = sender
                if msg.get_type() == "GLOBAL_POSITION_INT":
                    positions[msg.get_srcSystem()] = msg
    assert sorted(senders) == [1, 2, 3] and len(set(senders.values())) == 3
    for system in (1, 2, 3):  # 2 s: ~10 positions (5 Hz), ~2 heartbeats
        assert 8 <= counts[(system, "GLOBAL_POSITION_INT")] <= 12
        assert 1 <= counts[(system, "HEARTBEAT")] <= 3
    # Vehicle 2 (system 2) stands 4 m east of vehicle 1 (and of the origin), 3 m up.
    east = positions[2]
    assert haversine_m(ORIGIN.lat_deg, ORIGIN.lon_deg, east.lat * 1e-7, east.lon * 1e-7) == \
        pytest.approx(4.0, abs=0.02)
    assert east.relative_alt == 3000
    # Commands to each vehicle, at the address it sends from: denied, nothing changes.
    for system, address in senders.items():
        arm = gcs.out.command_long_encode(system, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                          0, 21196, 0, 0, 0, 0, 0)  # force disarm in the air
        gcs_socket.sendto(gcs.frame(arm), address)
    acks: dict[int, int] = {}
    deadline = time.monotonic() + 3.0
    while len(acks) < 3 and time.monotonic() < deadline:
        if select.select([gcs_socket], [], [], 0.1)[0]:
            for msg in gcs.decode([gcs_socket.recv(65535)]):
                if msg.get_type() == "COMMAND_ACK" and msg.command == 400:
                    acks[msg.get_srcSystem()] = msg.result
    assert acks == {1: mav.MAV_RESULT_DENIED, 2: mav.MAV_RESULT_DENIED,
                    3: mav.MAV_RESULT_DENIED}
    assert all(v.armed for v in fleet.vehicles)
    assert [link.refused["COMMAND_LONG 400"] for link in fleet.gcs_links] == [1, 1, 1]
    assert sum("refused COMMAND_LONG 400" in line for line in said) == 3
