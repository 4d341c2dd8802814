"""swarm.mavlink.link.AutopilotLink against EmulatedVehicle over real UDP on 127.0.0.1.

Both ends are real pymavlink; ports come from the OS. A served vehicle is a small loop in a
background thread stepping the vehicle at 50 Hz wall clock (``fly`` + telemetry) and
answering every datagram at once. Waits are on conditions with deadlines, never sleeps (but
one, standing for the imports of an agent whose socket is already bound).
"""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle
from swarm.mavlink.link import (
    EXCLUSIVE_LISTEN_S,
    IDLE_STAMP_MS,
    AutopilotLink,
    LinkError,
    PositionSample,
)
from swarm.mavlink.parse import LOCAL_POSITION_NED, parse_bytes
from swarm.mavlink.sitl import free_udp_port
from swarm.mavlink.udpin import bind_udpin
from swarm.models import frames
from tests.mavlink.test_parse import ARDUPILOT_BOOT_TEXT

DT = 0.02
DRONE = 2
SYS = DRONE + 1
ORIGIN = np.array([100.0, -50.0, 0.0])
START = np.array([103.0, -46.0, 4.0])


class ServedVehicle:
    """EmulatedVehicle behind a VehicleEndpoint, stepped at 50 Hz by a background thread.

    ``intercept(message, now_s)`` may answer a parsed incoming message itself (returning the
    reply packets) instead of passing its datagram to the vehicle; it returns None to pass.
    ``heartbeat_period_s`` None: no periodic HEARTBEAT (only requested ones).
    """

    def __init__(self, vehicle: EmulatedVehicle, agent_port: int,
                 intercept: Callable[[Any, float], list[bytes] | None] | None = None,
                 heartbeat_period_s: float | None = 1.0) -> None:
        self.vehicle = vehicle
        self.heartbeat_period_s = heartbeat_period_s
        self.endpoint = VehicleEndpoint(("127.0.0.1", agent_port))
        self.intercept = intercept
        self.lock = threading.Lock()
        self.applied: list[np.ndarray] = []  # velocity flown at each step
        self.errors: list[BaseException] = []
        self._stop = threading.Event()
        self._parser = mav.MAVLink(None)
        self._parser.robust_parsing = True
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._t0 = time.monotonic()
        self._thread.start()

    def forge(self) -> Any:
        """A MAVLink encoder speaking as this vehicle (for intercept replies)."""
        return mav.MAVLink(None, srcSystem=self.vehicle.system_id, srcComponent=1)

    def _run(self) -> None:
        try:
            next_step = self._t0
            next_heartbeat = self._t0
            while not self._stop.is_set():
                now = time.monotonic()
                with self.lock:
                    if self.heartbeat_period_s is not None and now >= next_heartbeat:
                        self.endpoint.send([self.vehicle.heartbeat()])  # 1 Hz, as sim-world
                        next_heartbeat += self.heartbeat_period_s
                    for data in self.endpoint.poll():
                        self._deliver(data, now - self._t0)
                    if now >= next_step:
                        t = now - self._t0
                        self.vehicle.fly(DT, t)  # as sim-world's realtime loop
                        self.applied.append(self.vehicle.velocity_w)
                        self.endpoint.send(self.vehicle.telemetry(round(t * 1000), t))
                        next_step += DT
                        if next_step < now:
                            next_step = now + DT
                select.select([self.endpoint], [], [], max(0.0, next_step - time.monotonic()))
        except BaseException as exc:  # surfaced by stop()
            self.errors.append(exc)

    def _deliver(self, data: bytes, t: float) -> None:
        if self.intercept is not None:
            msgs = self._parser.parse_buffer(data) or []
            if len(msgs) == 1:
                replies = self.intercept(msgs[0], t)
                if replies is not None:
                    self.endpoint.send(replies)
                    return
        self.endpoint.send(self.vehicle.receive(data, t))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.endpoint.close()
        assert not self._thread.is_alive()
        assert not self.errors, self.errors


@pytest.fixture
def logs() -> list[str]:
    return []


def make_link(flavour: str, logs: list[str], **kw: Any) -> AutopilotLink:
    return AutopilotLink("udpin:127.0.0.1:0", DRONE, flavour, ORIGIN,  # type: ignore[arg-type]
                         log=logs.append, **kw)


@pytest.fixture
def served() -> Iterator[Callable[..., tuple[AutopilotLink, ServedVehicle]]]:
    made: list[tuple[AutopilotLink, ServedVehicle]] = []

    def factory(flavour: str, logs: list[str], *, link_flavour: str | None = None,
                intercept: Any = None, heartbeat_period_s: float | None = 1.0,
                start: str = "air") -> tuple[AutopilotLink, ServedVehicle]:
        link = make_link(link_flavour or flavour, logs)
        vehicle = EmulatedVehicle(DRONE, flavour, START, ORIGIN,  # type: ignore[arg-type]
                                  start=start)  # type: ignore[arg-type]
        assert link.local_address is not None
        server = ServedVehicle(vehicle, link.local_address[1], intercept, heartbeat_period_s)
        made.append((link, server))
        return link, server

    yield factory
    for link, server in made:
        server.stop()
        link.close()




def pump_until(link: AutopilotLink, condition: Callable[[], bool], timeout: float = 3.0,
               *, velocity: np.ndarray | None = None) -> bool:
    """Drain the link (sending ``velocity`` every 20 ms if given) until condition()."""
    deadline = time.monotonic() + timeout
    last_send = 0.0
    while time.monotonic() < deadline:
        link.poll()
        if condition():
            return True
        if velocity is not None and time.monotonic() - last_send >= DT:
            link.send_velocity(velocity, 7)
            last_send = time.monotonic()
        link.wait_readable(0.01)
    return False


def newest_is(link: AutopilotLink, time_boot_ms: int) -> Callable[[], bool]:
    """Whether the link's newest position sample is the one stamped ``time_boot_ms``."""

    def check() -> bool:
        sample = link.latest_position()
        return sample is not None and sample.time_boot_ms == time_boot_ms

    return check


# ---------------------------------------------------------------- full handshake and flight
EXPECTED_HANDSHAKE = {  # the stages each start logs, in this order
    ("px4", "air"): ["vehicle in the air", "OFFBOARD accepted", "ARM already in effect",
                     "ready (OFFBOARD, armed)"],
    ("px4", "ground"): ["vehicle on the ground", "streaming position setpoints at the start",
                        "OFFBOARD accepted", "ARM accepted", "climb done",
                        "ready (OFFBOARD, armed, at the start)"],
    ("ardupilot", "air"): ["requesting LOCAL_POSITION_NED", "vehicle in the air",
                           "GUIDED already in effect", "already in the air: no takeoff",
                           "ready (GUIDED, armed, airborne)"],
    ("ardupilot", "ground"): ["vehicle on the ground", "GUIDED accepted", "ARM accepted",
                              "TAKEOFF to 4.00 m accepted", "climb done",
                              "ready (GUIDED, armed, airborne)"],
}


@pytest.mark.parametrize(("flavour", "start"), list(EXPECTED_HANDSHAKE))
def test_handshake_then_fly_a_velocity_setpoint(flavour: str, start: str, served: Any,
                                                logs: list[str]) -> None:
    link, server = served(flavour, logs, start=start)
    # From the ground: a climb to the start (4 m up; ArduPilot: 3 s spool-up first).
    link.handshake(timeout_s=30.0, start_position_w=START)
    with server.lock:
        vehicle = server.vehicle
        assert vehicle.armed and vehicle.in_setpoint_mode and not vehicle.failsafe_active
        assert vehicle.accepting_setpoints
        assert vehicle.mode == link.mode == ("OFFBOARD" if flavour == "px4" else "GUIDED")
        assert vehicle.airborne and vehicle.rejected_frames == 0
        assert vehicle.landed_state == mav.MAV_LANDED_STATE_IN_AIR
        if start == "ground":  # arrived: within the link's tolerance of the start height
            assert abs(vehicle.position_w[2] - START[2]) <= 0.3
        n_before = len(server.applied)
    assert link.armed
    said = [line.removeprefix(f"drone {DRONE}: ") for line in logs]
    where = 0
    for expected in EXPECTED_HANDSHAKE[(flavour, start)]:
        found = [i for i, line in enumerate(said) if i >= where and line.startswith(expected)]
        assert found, (expected, said)
        where = found[0] + 1
    if start == "air":
        assert not any(line.startswith(("TAKEOFF", "climbing")) for line in said), said
    # Settle: the idle (zero) setpoints hold it still before the step.
    link.send_velocity(np.zeros(3), 6)
    assert pump_until(link, lambda: np.array_equal(server.applied[-1], np.zeros(3)), 5.0,
                      velocity=np.zeros(3))
    with server.lock:
        start_w = server.vehicle.position_w
        n_before = len(server.applied)

    # fly 1.0 m/s east, -0.5 m/s north, +0.25 m/s up for ~0.5 s, then stop
    u = np.array([1.0, -0.5, 0.25])
    u_link = frames.velocity_over_link(u)
    t_end = time.monotonic() + 0.5
    assert pump_until(link, lambda: time.monotonic() >= t_end, 1.0, velocity=u)
    link.send_velocity(np.zeros(3), 8)
    assert pump_until(link, lambda: np.array_equal(server.applied[-1], np.zeros(3)))
    with server.lock:
        steps = server.applied[n_before:]
        end = server.vehicle.position_w
    moving = [s for s in steps if np.any(s != 0)]
    assert all(np.array_equal(s, u_link) for s in moving)  # bit-exact, never clamped here
    assert 0.35 <= len(moving) * DT <= 0.8
    displacement = end - start_w
    np.testing.assert_allclose(displacement, len(moving) * DT * u_link, rtol=0, atol=1e-10)
    assert displacement[0] > 0.3 and displacement[1] < -0.15 and displacement[2] > 0.08

    # the agent sees the same position (float32 over the link), newest sample first
    assert pump_until(link, lambda: (s := link.latest_position()) is not None
                      and np.array_equal(s.velocity_w, np.zeros(3)))
    sample = link.latest_position()
    assert sample is not None
    with server.lock:
        truth = server.vehicle.position_w
    assert np.max(np.abs(sample.position_w - truth)) < 1e-4 + 1e-9
    assert link.rejected_frames == 0


def test_arm_denied_once_is_retried_and_logged(served: Any, logs: list[str]) -> None:
    denied: list[int] = []

    def deny_first_arm(msg: Any, t: float) -> list[bytes] | None:
        if msg.get_type() == "COMMAND_LONG" and msg.command == 400 and not denied:
            denied.append(msg.confirmation)
            forge = server.forge()
            ack = forge.command_ack_encode(400, mav.MAV_RESULT_FAILED, 0, 0, SYS,
                                           mav.MAV_COMP_ID_ONBOARD_COMPUTER)
            return [ack.pack(forge)]
        return None

    link, server = served("px4", logs, intercept=deny_first_arm, start="ground")
    link.handshake(timeout_s=20.0, start_position_w=START, retries=3)
    assert denied == [0]
    # FAILED is "not now" (PX4/ArduPilot pre-arm checks): asked again until the deadline
    assert (f"drone {DRONE}: ARM denied (result 4 MAV_RESULT_FAILED); asking again every 1 s"
            in logs)
    assert f"drone {DRONE}: ARM accepted" in logs
    assert link.armed and link.mode == "OFFBOARD"


def test_handshake_gives_up_with_one_line_error(served: Any, logs: list[str]) -> None:
    def swallow_mode_changes(msg: Any, t: float) -> list[bytes] | None:
        if msg.get_type() == "COMMAND_LONG" and msg.command == 176:
            return []  # no ACK at all
        return None

    link, _ = served("px4", logs, intercept=swallow_mode_changes)
    with pytest.raises(LinkError) as err:
        link.handshake(timeout_s=10.0, retries=2, ack_timeout_s=0.2)
    text = str(err.value)
    assert "\n" not in text
    assert text == (f"drone {DRONE}: OFFBOARD failed after 2 attempts on {link.url}: "
                    f"got no ACK within 0.2 s: it needs a setpoint stream (COM_OF_LOSS_T) "
                    f"and a position estimate")
    assert f"drone {DRONE}: OFFBOARD got no ACK within 0.2 s, retry 2/2" in logs


def test_handshake_overall_timeout(served: Any, logs: list[str]) -> None:
    def swallow(msg: Any, t: float) -> list[bytes] | None:
        return [] if msg.get_type() == "COMMAND_LONG" else None

    link, _ = served("ardupilot", logs, intercept=swallow)
    with pytest.raises(LinkError, match=r"handshake did not complete within 0\.5 s") as err:
        link.handshake(timeout_s=0.5, retries=5, ack_timeout_s=1.0)
    assert "\n" not in str(err.value)


def test_flavour_mismatch_is_reported(served: Any, logs: list[str]) -> None:
    link, _ = served("ardupilot", logs, link_flavour="px4")
    with pytest.raises(LinkError) as err:
        link.wait_heartbeat(3.0)
    assert str(err.value) == (f"drone {DRONE}: system {SYS} on {link.url} reports autopilot "
                              f"ArduPilot but flavour 'px4' is configured")


def test_a_heartbeat_is_requested_as_soon_as_the_vehicle_is_heard(served: Any,
                                                                   logs: list[str]) -> None:
    """A vehicle that streams LOCAL_POSITION_NED but sends no periodic HEARTBEAT answers
    MAV_CMD_REQUEST_MESSAGE: the link does not wait for a 1 Hz heartbeat."""
    link, _server = served("px4", logs, heartbeat_period_s=None)
    started = time.monotonic()
    link.wait_heartbeat(timeout_s=5.0)
    assert time.monotonic() - started < 1.0
    assert link.autopilot == mav.MAV_AUTOPILOT_PX4 and link.mode == "LOITER"


def test_no_heartbeat_error_names_the_port_base() -> None:
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}", DRONE, "px4", ORIGIN, log=lambda _: None)
    try:
        t0 = time.monotonic()
        with pytest.raises(LinkError) as err:
            link.wait_heartbeat(0.3)
        assert 0.25 <= time.monotonic() - t0 < 2.0
        assert str(err.value) == (f"no HEARTBEAT from system {SYS} on udpin:127.0.0.1:{port} "
                                  f"within 0.3 s: is the vehicle (sim-world --mavlink-base "
                                  f"{port - DRONE}, or an autopilot) sending to port {port}?")
        # a vehicle with the wrong system id talking to this port is named in the error
        other = EmulatedVehicle(DRONE + 1, "px4", START, ORIGIN)
        with VehicleEndpoint(("127.0.0.1", port)) as ep:
            ep.send([other.heartbeat()])
            with pytest.raises(LinkError, match=(
                    rf"autopilot system 4 \(PX4\) at 127\.0\.0\.1:\d+ on "
                    rf"udpin:127\.0\.0\.1:{port} is not ours \(system 3\): refusing to fly it")):
                link.wait_heartbeat(0.3)
        assert link.foreign_frames >= 1
    finally:
        link.close()


def test_port_already_in_use_is_a_link_error() -> None:
    first = make_link("px4", [])
    try:
        assert first.local_address is not None
        url = f"udpin:127.0.0.1:{first.local_address[1]}"
        with pytest.raises(LinkError, match="already using that port") as err:
            AutopilotLink(url, DRONE, "px4", ORIGIN, log=lambda _: None)
        assert "\n" not in str(err.value)
    finally:
        first.close()


# ---------------------------------------------------------------- reading samples
@pytest.fixture
def pair() -> Iterator[tuple[AutopilotLink, EmulatedVehicle, VehicleEndpoint]]:
    """A link and a vehicle endpoint with no serving thread: the test drives the vehicle."""
    link = make_link("px4", [])
    assert link.local_address is not None
    vehicle = EmulatedVehicle(DRONE, "px4", START, ORIGIN)
    endpoint = VehicleEndpoint(("127.0.0.1", link.local_address[1]))
    yield link, vehicle, endpoint
    endpoint.close()
    link.close()


def _emit(vehicle: EmulatedVehicle, endpoint: VehicleEndpoint, stamps: range,
          *, coalesce: bool = False) -> list[np.ndarray]:
    truths = []
    packets: list[bytes] = []
    for stamp in stamps:
        vehicle.integrate(DT, [0.5, 0.25, -0.125])
        packets.extend(vehicle.telemetry(stamp, stamp / 1000.0))
        truths.append(vehicle.position_w)
        if not coalesce:
            endpoint.send(packets)
            packets = []
    if coalesce:
        endpoint.send(packets, coalesce=True)
    return truths


def test_latest_position_returns_the_newest_of_many_queued(pair: Any) -> None:
    link, vehicle, endpoint = pair
    assert link.latest_position() is None
    truths = _emit(vehicle, endpoint, range(0, 4000, 20))  # 200 queued samples
    assert pump_until(link, newest_is(link, 3980))
    sample = link.latest_position()
    assert isinstance(sample, PositionSample) and sample.time_boot_ms == 3980
    np.testing.assert_array_equal(sample.position_w,
                                  frames.position_over_link(truths[-1], ORIGIN))  # bit-exact
    np.testing.assert_array_equal(sample.velocity_w,
                                  frames.velocity_over_link([0.5, 0.25, -0.125]))
    assert link.latest_position() is sample  # nothing new: the same newest sample
    # several packets in one datagram, with junk in between datagrams
    junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with junk:
        assert link.local_address is not None
        junk.sendto(b"\xfd\x09garbage-garbage", link.local_address)
        bad = bytearray(vehicle.telemetry(9999, 99.0)[0])
        bad[-2] ^= 0x55  # bad CRC
        junk.sendto(bytes(bad), link.local_address)
        truths = _emit(vehicle, endpoint, range(4000, 4100, 20), coalesce=True)
        assert pump_until(link, newest_is(link, 4080))
    sample = link.latest_position()
    assert sample is not None and sample.time_boot_ms == 4080
    np.testing.assert_array_equal(sample.position_w,
                                  frames.position_over_link(truths[-1], ORIGIN))
    assert link.rejected_frames >= 1
    assert not any(k.startswith(("handler_error", "receive_error")) for k in link.rejections)


def test_wait_position_picks_the_exact_stamp(pair: Any) -> None:
    link, vehicle, endpoint = pair
    truths = _emit(vehicle, endpoint, range(100, 111))
    sample = link.wait_position(105, timeout_s=2.0)
    assert sample.time_boot_ms == 105
    np.testing.assert_array_equal(sample.position_w,
                                  frames.position_over_link(truths[5], ORIGIN))
    assert link.wait_position(110, 2.0).time_boot_ms == 110
    assert link.wait_position(101, 0.0).time_boot_ms == 101  # already seen: no waiting
    t0 = time.monotonic()
    with pytest.raises(LinkError) as err:
        link.wait_position(999, timeout_s=0.2)
    assert time.monotonic() - t0 < 1.5
    assert str(err.value) == (f"drone {DRONE}: no LOCAL_POSITION_NED stamped 999 ms from system "
                              f"{SYS} on {link.url} within 0.2 s (newest seen: 110 ms)")


def test_position_at_pairs_a_stamp_without_waiting(pair: Any) -> None:
    """A realtime agent pairs a camera frame with the pose stamped like it: the kept sample if
    there is one (bit-exact), None at once otherwise (the last 512 are kept)."""
    link, vehicle, endpoint = pair
    truths = []
    for first in (0, 200, 400):  # 600 samples in three bursts (a socket buffer each), 512 kept
        truths += _emit(vehicle, endpoint, range(20 * first, 20 * (first + 200), 20))
        assert pump_until(link, newest_is(link, 20 * (first + 199)))
    sample = link.position_at(11000)
    assert sample is not None and sample.time_boot_ms == 11000
    np.testing.assert_array_equal(sample.position_w,
                                  frames.position_over_link(truths[550], ORIGIN))
    t0 = time.monotonic()
    assert link.position_at(11001) is None  # no such stamp
    assert link.position_at(20 * 87) is None  # dropped: older than the last 512
    assert link.position_at(20 * 88) is not None
    assert time.monotonic() - t0 < 0.5


def test_samples_from_another_system_are_ignored(pair: Any) -> None:
    link, _, endpoint = pair
    stranger = EmulatedVehicle(DRONE + 3, "px4", START, ORIGIN)
    endpoint.send(stranger.telemetry(40, 0.04))
    with pytest.raises(LinkError):
        link.wait_position(40, 0.2)
    assert link.foreign_frames >= 1 and link.rejected_frames == 0


# ---------------------------------------------------------------- sending
def _received(endpoint: VehicleEndpoint, count: int, timeout: float = 2.0) -> list[Any]:
    parser = mav.MAVLink(None)
    msgs: list[Any] = []
    deadline = time.monotonic() + timeout
    while len(msgs) < count and time.monotonic() < deadline:
        select.select([endpoint], [], [], 0.05)
        for data in endpoint.poll():
            msgs.extend(parser.parse_buffer(data) or [])
    return msgs


def _introduce(link: AutopilotLink, vehicle: EmulatedVehicle,
               endpoint: VehicleEndpoint) -> None:
    """udpin learns where to send from the first datagram it receives."""
    endpoint.send([vehicle.heartbeat()])
    link.wait_heartbeat(2.0)


def test_send_velocity_packet_contents(pair: Any) -> None:
    link, vehicle, endpoint = pair
    _introduce(link, vehicle, endpoint)
    u = np.array([0.1, -2.7, 1.3])
    link.send_velocity(u, 123_460)
    msgs = [m for m in _received(endpoint, 2) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    (sp,) = msgs
    assert sp.get_msgbuf()[0] == 0xFD  # MAVLink 2
    assert (sp.get_srcSystem(), sp.get_srcComponent()) == (SYS, mav.MAV_COMP_ID_ONBOARD_COMPUTER)
    assert (sp.target_system, sp.target_component) == (SYS, 1)
    assert sp.coordinate_frame == mav.MAV_FRAME_LOCAL_NED and sp.type_mask == 0x0DC7
    assert sp.time_boot_ms == 123_460
    decoded = frames.ned_to_enu([sp.vx, sp.vy, sp.vz])
    np.testing.assert_array_equal(decoded, frames.velocity_over_link(u))
    assert sp.vx == pytest.approx(-2.7, abs=1e-6) and sp.vy == pytest.approx(0.1, abs=1e-7)
    assert sp.vz == pytest.approx(-1.3, abs=1e-6)
    with pytest.raises(ValueError, match="uint32"):
        link.send_velocity(u, 2**32)
    with pytest.raises(ValueError, match="3-vector"):
        link.send_velocity([1.0, 2.0], 0)
    link.send_velocity([1e39, 0.0, 0.0], 0)  # beyond float32: sent as inf, the vehicle holds


def test_keepalive_sends_idle_setpoints_at_most_every_100_ms(pair: Any) -> None:
    link, vehicle, endpoint = pair
    _introduce(link, vehicle, endpoint)
    now = time.monotonic()
    link.keepalive(now)
    link.keepalive(now + 0.05)  # too soon: nothing
    link.keepalive(now + 0.2)
    msgs = _received(endpoint, 3)
    setpoints = [m for m in msgs if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert len(setpoints) == 2
    assert all(m.time_boot_ms == IDLE_STAMP_MS and (m.vx, m.vy, m.vz) == (0, 0, 0)
               for m in setpoints)
    heartbeats = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert heartbeats and heartbeats[0].type == mav.MAV_TYPE_ONBOARD_CONTROLLER


def test_garbage_at_the_agent_port_is_counted_never_raised(pair: Any) -> None:
    link, vehicle, endpoint = pair
    rng = np.random.default_rng(11)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:
        assert link.local_address is not None
        for size in (1, 7, 64, 300, 2000):
            junk.sendto(rng.integers(0, 256, size, dtype=np.uint8).tobytes(),
                        link.local_address)
        junk.sendto(vehicle.heartbeat()[:11], link.local_address)  # truncated
    endpoint.send(vehicle.telemetry(0, 0.0))  # right after the truncated frame
    endpoint.send(vehicle.telemetry(20, 0.02))
    assert link.wait_position(0, 2.0).time_boot_ms == 0  # not swallowed by the truncated one
    sample = link.wait_position(20, 2.0)
    assert sample.time_boot_ms == 20
    assert link.rejections["truncated"] >= 1 and link.rejections["bad_data"] >= 1
    assert not any(k.startswith(("handler_error", "receive_error")) for k in link.rejections)



# ---------------------------------------------------------------- console text
def _sample(stamp: int) -> bytes:
    """A LOCAL_POSITION_NED of the vehicle (ArduPilot streams one only once asked)."""
    return LOCAL_POSITION_NED.pack(mav.MAVLink(None, srcSystem=SYS, srcComponent=1), stamp,
                                   *[0.0] * 6)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_ardupilots_console_text_is_logged_not_rejected(flavour: str, logs: list[str]) -> None:
    """ArduPilot's console is its first MAVLink port: while it boots it prints its gyro
    calibration there, a datagram per print, between its frames. Not a rejected frame from
    ArduPilot (its lines are logged); from PX4, which prints nothing there, junk. A broken
    frame or junk from ArduPilot is still a rejection."""
    link = make_link(flavour, logs)
    vehicle = EmulatedVehicle(DRONE, flavour, START, ORIGIN)  # type: ignore[arg-type]
    assert link.local_address is not None
    bad_crc = bytearray(vehicle.heartbeat())
    bad_crc[-1] ^= 0xFF
    try:
        with VehicleEndpoint(("127.0.0.1", link.local_address[1])) as autopilot:
            autopilot.send([vehicle.heartbeat(), *ARDUPILOT_BOOT_TEXT])
            autopilot.send([_sample(40)])
            assert link.wait_position(40, 2.0).time_boot_ms == 40
            if flavour == "ardupilot":
                assert link.rejected_frames == 0 and link.rejections == Counter()
                assert link.console_text_bytes == len(b"".join(ARDUPILOT_BOOT_TEXT))
                assert link.peer == autopilot.local_address  # pinned at its heartbeat
                assert f"drone {DRONE}: autopilot console (text on its MAVLink port, not " \
                       f"MAVLink; not a rejected frame): Init Gyro**" in logs
            else:
                assert link.rejections == Counter({"bad_data": len(ARDUPILOT_BOOT_TEXT)})
                assert link.console_text_bytes == 0
                assert not any("console" in line for line in logs)
            rejected = link.rejected_frames
            autopilot.send([bytes(bad_crc), bytes(range(0xFD))])
            autopilot.send([_sample(60)])
            assert link.wait_position(60, 2.0).time_boot_ms == 60
            assert link.rejections["bad_data"] == rejected + 2 == link.rejected_frames
    finally:
        link.close()


def test_console_text_before_the_first_frame_of_a_stream_is_not_rejected(
        logs: list[str]) -> None:
    """ArduPilot SITL's first port is a TCP server: a link that connects while it boots reads
    its console text in the stream, before and between frames (pymavlink cuts it where it
    reads). A frame broken in the stream is still a rejection."""
    vehicle = EmulatedVehicle(DRONE, "ardupilot", START, ORIGIN)
    bad_crc = bytearray(vehicle.heartbeat())
    bad_crc[-1] ^= 0xFF
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        link = AutopilotLink(f"tcp:127.0.0.1:{port}", DRONE, "ardupilot", ORIGIN,
                             log=logs.append)
        try:
            autopilot, _ = server.accept()
            with autopilot:
                autopilot.sendall(b"".join(ARDUPILOT_BOOT_TEXT[:-1]))
                autopilot.sendall(vehicle.heartbeat() + b"***" + vehicle.heartbeat())
                autopilot.sendall(ARDUPILOT_BOOT_TEXT[-1] + _sample(40))
                assert link.wait_position(40, 2.0).time_boot_ms == 40
                assert link.rejected_frames == 0
                assert link.console_text_bytes == len(b"".join(ARDUPILOT_BOOT_TEXT)) + 3
                assert any(line.endswith(": Init Gyro*****") for line in logs), logs
                autopilot.sendall(bytes(bad_crc) + _sample(60))
                assert link.wait_position(60, 2.0).time_boot_ms == 60
                assert link.rejections == Counter({"bad_data": 1})
        finally:
            link.close()


def test_console_text_is_logged_a_line_at_a_time_up_to_a_limit(logs: list[str]) -> None:
    link = make_link("ardupilot", logs)
    vehicle = EmulatedVehicle(DRONE, "ardupilot", START, ORIGIN)
    assert link.local_address is not None
    try:
        with VehicleEndpoint(("127.0.0.1", link.local_address[1])) as autopilot:
            autopilot.send([vehicle.heartbeat()])
            autopilot.send([f"line {i}\n".encode() for i in range(30)] + [b"no newline"])
            autopilot.send([_sample(40)])
            assert link.wait_position(40, 2.0).time_boot_ms == 40
            console = [line for line in logs if "console" in line]
            assert console[0].endswith(": line 0") and console[19].endswith(": line 19")
            assert len(console) == 21 and "not logged" in console[20]
            assert link.console_text_bytes == sum(len(f"line {i}\n") for i in range(30)) + 10
            assert link.rejected_frames == 0
    finally:
        link.close()

# ---------------------------------------------------------------- udpin peer pinning
def _datagrams(sock: socket.socket, timeout: float = 0.3) -> list[bytes]:
    """Every datagram ``sock`` receives until it has been quiet for ``timeout``."""
    got = []
    while select.select([sock], [], [], timeout)[0]:
        got.append(sock.recv(65535))
    return got


def test_udpin_pins_the_vehicle_address_and_counts_other_senders() -> None:
    """pymavlink's udpin sends to every address that ever sent it a datagram: one forged
    datagram got a copy of every setpoint. The vehicle's address is pinned at its first valid
    frame, for good; anything from elsewhere (junk, a valid frame of the vehicle's own
    system, a NaN sample) is counted and dropped unread, however long the vehicle is quiet."""
    link = make_link("px4", [])
    vehicle = EmulatedVehicle(DRONE, "px4", START, ORIGIN)
    endpoint = VehicleEndpoint(("127.0.0.1", link.local_address[1]))
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    forger.bind(("127.0.0.1", 0))
    try:
        _introduce(link, vehicle, endpoint)
        as_the_vehicle = mav.MAVLink(None, srcSystem=SYS, srcComponent=1)
        forged = [b"", b"\xfd\x05junk", vehicle.telemetry(1234, 1.0)[0],
                  LOCAL_POSITION_NED.pack(as_the_vehicle, 1236, *[math.nan] * 6),
                  vehicle.heartbeat() + b"junk"]
        for datagram in forged:
            forger.sendto(datagram, link.local_address)
        endpoint.send(vehicle.telemetry(40, 0.04))
        assert link.wait_position(40, 2.0).time_boot_ms == 40
        assert link.rejections["foreign_address"] == len(forged) == link.rejected_frames
        with pytest.raises(LinkError):
            link.wait_position(1234, 0.05)  # the forged sample never counted
        link.send_velocity([1.0, 0.0, 0.0], 40)
        assert _datagrams(forger) == []  # no copy of the setpoint
        assert any(m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
                   for m in _received(endpoint, 1))
        with VehicleEndpoint(("127.0.0.1", link.local_address[1])) as elsewhere:
            elsewhere.send(vehicle.telemetry(80, 0.08))  # valid, but from another address
            with pytest.raises(LinkError):
                link.wait_position(80, 0.3)
            assert link.rejections["foreign_address"] == len(forged) + 1
    finally:
        forger.close()
        endpoint.close()
        link.close()


# ---------------------------------------------------------------- exactly one vehicle
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_a_second_autopilot_is_refused_and_never_commanded(flavour: str, served: Any,
                                                           logs: list[str]) -> None:
    """Two autopilots of the same system id send to the agent's port (a SITL left running
    beside an emulated run): the link keeps the first, stops with one line naming both, and
    the second never gets a command or a setpoint."""
    link, server = served(flavour, logs, start="ground")
    assert pump_until(link, lambda: link.peer is not None, 5.0)  # the first one is pinned
    intruder = EmulatedVehicle(DRONE, flavour, START, ORIGIN, start="ground")  # same system
    received: list[str] = []
    with VehicleEndpoint(("127.0.0.1", link.local_address[1])) as other:
        stop = threading.Event()

        def intrude() -> None:  # heartbeats at 5 Hz, every reply recorded and answered
            while not stop.is_set():
                other.send([intruder.heartbeat()])
                for data in other.poll():
                    received.extend(m.get_type() for m in parse_bytes(
                        mav.MAVLink(None), data, Counter(), datagram=True))
                    other.send(intruder.receive(data, time.monotonic()))
                stop.wait(0.2)

        thread = threading.Thread(target=intrude, daemon=True)
        thread.start()
        try:
            with pytest.raises(LinkError) as err:
                link.handshake(timeout_s=15.0, start_position_w=START)
        finally:
            stop.set()
            thread.join(timeout=5.0)
        other_address = other.local_address
    text = str(err.value)
    assert "\n" not in text
    first = server.endpoint.local_address
    assert f"{first[0]}:{first[1]}" in text and f"{other_address[0]}:{other_address[1]}" in text
    assert "second autopilot" in text, text
    assert not intruder.armed and intruder.mode == ("LOITER" if flavour == "px4" else "STABILIZE")
    assert "COMMAND_LONG" not in received and "SET_POSITION_TARGET_LOCAL_NED" not in received
    with server.lock:
        assert not server.vehicle.armed  # refused before the first was armed either
    assert not link.end_mission("hold")  # nothing was commanded: nothing to end


# ---------------------------------------------------------------- a socket bound early
# swarm-agent binds its udpin socket before its imports (swarm.mavlink.udpin) and the link
# takes it over: the listening window counts from the bind, so it must also hear what
# arrived before the link existed.
MOVING_COMMANDS = {mav.MAV_CMD_DO_SET_MODE, mav.MAV_CMD_COMPONENT_ARM_DISARM,
                   mav.MAV_CMD_NAV_TAKEOFF}


def test_a_link_on_an_early_bound_socket_listens_from_the_bind(logs: list[str]) -> None:
    """The vehicle sends to the port for a while before the link exists; the link hears it,
    answers from the bound port, and sends nothing that arms or moves the vehicle before
    EXCLUSIVE_LISTEN_S after the bind, nor a whole window after its own start."""
    flavour = "px4"  # in the air: its first setpoint and OFFBOARD move it
    bound = bind_udpin(f"udpin:127.0.0.1:{free_udp_port()}")
    port = bound.sock.getsockname()[1]
    sent: list[tuple[float, str]] = []  # (monotonic s, what) of every command and setpoint

    def record(msg: Any, t: float) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG" and msg.command in MOVING_COMMANDS:
            sent.append((time.monotonic(), f"command {msg.command}"))
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            sent.append((time.monotonic(), "setpoint"))

    vehicle = EmulatedVehicle(DRONE, flavour, START, ORIGIN)  # type: ignore[arg-type]
    server = ServedVehicle(vehicle, port, lambda msg, t: record(msg, t))
    try:
        # Its datagrams wait in the kernel for a link that does not exist yet, as while
        # swarm-agent imports (~1 s of a 6-drone launch on two cores).
        assert select.select([bound.sock], [], [], 5.0)[0]
        time.sleep(1.2)  # the scenario, not a wait: time passes before the link exists
        created_s = time.monotonic()
        link = AutopilotLink(bound.url, DRONE, flavour, ORIGIN,  # type: ignore[arg-type]
                             log=logs.append, bound=bound)
        try:
            assert link.local_address == ("127.0.0.1", port)
            assert link.file_descriptor is not None
            assert not os.get_inheritable(link.file_descriptor)
            link.handshake(timeout_s=30.0, start_position_w=START)
            with server.lock:  # everything came from the bound port
                assert server.endpoint.peer_address == ("127.0.0.1", port)
                assert server.endpoint.peer_changes == 0
            assert sent, "the handshake commanded nothing"
            first_s = min(t for t, _ in sent)
            assert first_s >= bound.bound_s + EXCLUSIVE_LISTEN_S, sent
            assert first_s < created_s + EXCLUSIVE_LISTEN_S, (first_s - created_s, sent)
            with server.lock:
                assert server.vehicle.armed and server.vehicle.in_setpoint_mode
        finally:
            link.close()
    finally:
        server.stop()


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_a_second_autopilot_heard_before_the_link_existed_is_refused(flavour: str,
                                                                     logs: list[str]) -> None:
    """Both autopilots' heartbeats arrived while the agent was still importing: the link
    reads them from the bound socket, keeps the first and refuses to fly."""
    bound = bind_udpin(f"udpin:127.0.0.1:{free_udp_port()}")
    port = bound.sock.getsockname()[1]
    first = VehicleEndpoint(("127.0.0.1", port))
    other = VehicleEndpoint(("127.0.0.1", port))
    link = None
    try:
        make = EmulatedVehicle
        first.send([make(DRONE, flavour, START, ORIGIN, start="ground").heartbeat()])
        assert select.select([bound.sock], [], [], 5.0)[0]  # queued first
        other.send([make(DRONE, flavour, START, ORIGIN, start="ground").heartbeat()])
        link = AutopilotLink(bound.url, DRONE, flavour, ORIGIN,  # type: ignore[arg-type]
                             log=logs.append, bound=bound)
        with pytest.raises(LinkError) as err:
            link.handshake(timeout_s=5.0, start_position_w=START)
        text = str(err.value)
        assert "second autopilot" in text, text
        for endpoint in (first, other):
            host, number = endpoint.local_address
            assert f"{host}:{number}" in text, text
        assert other.poll() == []  # nothing was ever sent to the second one
    finally:
        if link is not None:
            link.close()
        first.close()
        other.close()


# ---------------------------------------------------------------- what the autopilot says
def test_a_refusal_quotes_what_the_autopilot_said(served: Any, logs: list[str]) -> None:
    """ArduPilot says why in STATUSTEXT right behind a refused ARM: the log line and the
    final error quote it."""
    def refuse_arm(msg: Any, t: float) -> list[bytes] | None:
        if msg.get_type() == "COMMAND_LONG" and msg.command == 400:
            forge = server.forge()
            # ArduPilot says why while it checks, so the text comes right before the ACK
            text = forge.statustext_encode(mav.MAV_SEVERITY_CRITICAL,
                                           b"PreArm: Throttle below Failsafe")
            ack = forge.command_ack_encode(400, mav.MAV_RESULT_DENIED, 0, 0, SYS, 191)
            return [text.pack(forge), ack.pack(forge)]
        return None

    link, server = served("ardupilot", logs, intercept=refuse_arm, start="ground")
    with pytest.raises(LinkError) as err:
        link.handshake(timeout_s=15.0, start_position_w=START, retries=2, ack_timeout_s=0.5)
    text = str(err.value)
    assert text.startswith(f"drone {DRONE}: ARM failed after 2 attempts on {link.url}: "
                           f"denied (result 2 MAV_RESULT_DENIED); autopilot says: "
                           f"'PreArm: Throttle below Failsafe'"), text
    assert "pre-arm checks fail" in text  # what the operator can do
    assert any("retry 2/2" in line and "PreArm: Throttle below Failsafe" in line
               for line in logs), logs


def test_position_is_awaited_up_to_the_deadline(served: Any, logs: list[str]) -> None:
    """A freshly booted ArduCopter accepts the stream request but sends no position until its
    EKF has an origin: the link asks again and waits (not a fixed number of tries)."""
    opened_at = time.monotonic() + 3.0
    requests: list[float] = []

    def no_position_yet(msg: Any, t: float) -> list[bytes] | None:
        if (msg.get_type() == "COMMAND_LONG" and msg.command == 511
                and msg.param1 == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED
                and time.monotonic() < opened_at):
            requests.append(t)
            forge = server.forge()
            return [forge.command_ack_encode(511, mav.MAV_RESULT_ACCEPTED, 0, 0, SYS,
                                             191).pack(forge)]
        return None

    link, server = served("ardupilot", logs, intercept=no_position_yet)
    link.handshake(timeout_s=20.0, start_position_w=START)
    up = [line for line in logs if "position stream up after" in line]
    assert up and float(up[0].split("after ")[1].split(" s")[0]) >= 2.5, logs
    assert len(requests) >= 2  # asked again (every 2 s), accepted each time, no give-up


# ---------------------------------------------------------------- a defined end
END_MODES = {("px4", "hold"): "LOITER", ("px4", "land"): "LAND", ("px4", "rtl"): "RTL",
             ("ardupilot", "hold"): "BRAKE", ("ardupilot", "land"): "LAND",
             ("ardupilot", "rtl"): "RTL"}
# The same modes as each autopilot names them (PX4's documentation and QGroundControl).
END_MODE_NAMES = {("px4", "hold"): "Hold", ("px4", "land"): "Land", ("px4", "rtl"): "Return",
                  ("ardupilot", "hold"): "BRAKE", ("ardupilot", "land"): "LAND",
                  ("ardupilot", "rtl"): "RTL"}


@pytest.mark.parametrize(("flavour", "action"), list(END_MODES))
def test_end_mission_stops_then_commands_the_end_action(flavour: str, action: str,
                                                        served: Any, logs: list[str]) -> None:
    link, server = served(flavour, logs)
    link.handshake(timeout_s=10.0, start_position_w=START)
    u = np.array([1.5, 0.0, 0.0])
    assert pump_until(link, lambda: np.array_equal(server.applied[-1], u), 3.0, velocity=u)
    assert link.end_mission(action)  # type: ignore[arg-type]
    expected = END_MODES[(flavour, action)]
    assert f"drone {DRONE}: end action {action} ({END_MODE_NAMES[(flavour, action)]}) " \
           f"accepted" in logs
    with server.lock:
        assert server.vehicle.mode == expected and not server.vehicle.failsafe_active
    # The vehicle slows down at once (zero velocity first, then its mode's own stop).
    assert pump_until(link, lambda: float(np.linalg.norm(server.vehicle.velocity_w[:2])) < 0.3,
                      5.0)
    if action == "land":
        assert pump_until(link, lambda: server.vehicle.velocity_w[2] < -0.3, 5.0)


def test_end_mission_refused_is_logged_not_raised(served: Any, logs: list[str]) -> None:
    def refuse_mode(msg: Any, t: float) -> list[bytes] | None:
        if msg.get_type() == "COMMAND_LONG" and msg.command == 176 and link.armed:
            forge = server.forge()
            return [forge.command_ack_encode(176, mav.MAV_RESULT_DENIED, 0, 0, SYS,
                                             191).pack(forge)]
        return None

    link, server = served("px4", logs, intercept=refuse_mode, start="ground")
    with pytest.raises(LinkError):
        link.handshake(timeout_s=3.0, start_position_w=START, retries=1, ack_timeout_s=0.3)
    assert not link.end_mission("land")
    assert any("end action land (Land) refused: result 2 MAV_RESULT_DENIED" in line
               for line in logs), logs


def test_send_tracked_packet_contents(pair: Any) -> None:
    """Position (local NED of the vehicle), velocity and acceleration feed-forward in one
    SET_POSITION_TARGET_LOCAL_NED; the pair's vehicle is PX4: type mask 0x0C00 (only yaw and
    yaw rate ignored). ArduPilot's mask ignores the acceleration (swarm.mavlink.parse)."""
    link, vehicle, endpoint = pair
    _introduce(link, vehicle, endpoint)
    position, velocity, acceleration = (np.array([104.0, -47.0, 4.5]), np.array([0.5, -1.0, 0.1]),
                                        np.array([2.0, 0.0, -1.0]))
    link.send_tracked(position, velocity, acceleration, 4_321)
    (sp,) = [m for m in _received(endpoint, 2) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert sp.type_mask == 0x0C00 and sp.time_boot_ms == 4_321
    np.testing.assert_allclose(
        frames.world_from_local_ned([sp.x, sp.y, sp.z], ORIGIN), position, atol=1e-5)
    np.testing.assert_allclose(frames.ned_to_enu([sp.vx, sp.vy, sp.vz]), velocity, atol=1e-6)
    np.testing.assert_allclose(frames.ned_to_enu([sp.afx, sp.afy, sp.afz]), acceleration,
                               atol=1e-6)


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_tracked_setpoints_pull_a_displaced_vehicle_onto_the_reference(
        flavour: str, served: Any, logs: list[str]) -> None:
    """The command reference at work on an emulated autopilot flying itself: a vehicle pushed
    0.4 m off the reference while it tracks u = 0.5 m/s east comes back onto it (its position
    loop; a velocity setpoint has nothing that would take the offset out)."""
    from swarm.models.command_reference import CommandReference

    link, server = served(flavour, logs)
    link.handshake(timeout_s=10.0, start_position_w=START)
    reference = CommandReference(reset_distance_m=1.0)
    u = (0.5, 0.0, 0.0)
    errors: list[float] = []
    pushed = False
    started = time.monotonic()
    last = started
    while time.monotonic() - started < 4.0:
        link.poll()
        sample = link.latest_position()
        now = time.monotonic()
        if sample is not None and now - last >= DT:
            if not pushed and now - started > 1.5:
                with server.lock:  # a gust: 0.4 m north, at once
                    server.vehicle.push([0.0, 0.4, 0.0])
                pushed = True
            p, v = sample.position_w.tolist(), sample.velocity_w.tolist()
            sp = reference.setpoint((p[0], p[1], p[2]), (v[0], v[1], v[2]), u, now - last)
            link.send_tracked(sp.position_w, sp.velocity_w, sp.acceleration_w, 5)
            errors.append(sp.position_error_m)
            last = now
        link.wait_readable(0.005)
    assert pushed and reference.resets == 0
    assert max(errors) > 0.3  # the push was seen
    assert errors[-1] < 0.05, errors[-20:]  # and taken out


def test_arducopter_is_sent_no_acceleration_a_lost_agent_would_leave_integrating() -> None:
    """GUIDED integrates an acceleration target into its velocity between setpoints: after a
    kill -9 the vehicle would speed up until GUID_TIMEOUT instead of coasting at the last
    velocity the others assume. Position and velocity only for ArduPilot; PX4 takes all."""
    from swarm.mavlink.parse import TRACKED_TYPE_MASK

    ignore_position, ignore_velocity, ignore_acceleration = 0x007, 0x038, 0x1C0
    ardupilot, px4 = TRACKED_TYPE_MASK["ardupilot"], TRACKED_TYPE_MASK["px4"]
    assert ardupilot & ignore_acceleration == ignore_acceleration
    assert ardupilot & (ignore_position | ignore_velocity) == 0
    assert px4 & (ignore_position | ignore_velocity | ignore_acceleration) == 0
