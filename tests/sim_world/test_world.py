"""sim_world.world.World in one process: what it puts on world/clock and when."""

from __future__ import annotations

import contextlib
import math
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

import sim_world.world as world_module
from sim_world.world import CLOCK_PERIOD_S, DeclarePublisher, World, WorldOptions
from swarm.launch.launcher import free_tcp_port, reserve_mavlink_base
from swarm.messages.wire import RELAY_HELD, RELAY_POSITION, BeaconWire
from swarm.net.session import declare_publisher, open_session, zenoh_config
from swarm.scenario.config import load_config
from tests.helpers.waiting import wait_until

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class _Captured:
    """A publisher that keeps what is put, and whether it came with a timestamp."""

    def __init__(self, block: bool) -> None:
        self.block = block
        self.payloads: list[bytes] = []
        self.stamped: list[bool] = []

    def put(self, payload: bytes, timestamp: object = None) -> None:
        self.payloads.append(payload)
        self.stamped.append(timestamp is not None)


class CapturedPublishers:
    """What a world declares its publishers with (``World(declare=...)``) when a test reads
    what it publishes: one ``_Captured`` per key, nothing sent."""

    def __init__(self) -> None:
        self.by_key: dict[str, _Captured] = {}

    def __call__(self, _session: object, key: str, *, block: bool = True) -> _Captured:
        assert key not in self.by_key, f"{key} declared twice"
        self.by_key[key] = _Captured(block)
        return self.by_key[key]

    def __getitem__(self, key: str) -> _Captured:
        return self.by_key[key]

    def total(self) -> int:
        return sum(len(publisher.payloads) for publisher in self.by_key.values())


@pytest.fixture
def captured() -> CapturedPublishers:
    return CapturedPublishers()


@pytest.fixture
def world(captured: CapturedPublishers) -> Iterator[World]:
    """A lockstep world whose publishers are ``captured``, and whose vehicles send to a
    MAVLink block it holds as a launcher does (``reserve_mavlink_base``'s lock): a
    launch-swarm in a test beside it never takes the same block (seen in CI: an agent of that
    swarm heard this world's vehicle 2 as a second autopilot on its port and refused to
    fly)."""
    config = load_config(CASE1)
    base, lock = reserve_mavlink_base(0, config.swarm.n_drones)
    with lock:
        made = World(WorldOptions(
            config=config, seed=0, run_id="clocktest",
            listen=(f"tcp/127.0.0.1:{free_tcp_port()}",), mavlink_base=base,
            log=lambda _line: None), declare=captured)
        try:
            yield made
        finally:
            made.close()


@contextlib.contextmanager
def external_world(run_id: str, declare: DeclarePublisher = declare_publisher
                   ) -> Iterator[tuple[World, Any]]:
    """A realtime world with external vehicles (it serves none) and a client session on its
    router, both closed on the way out."""
    port = free_tcp_port()
    made = World(WorldOptions(config=load_config(CASE1), seed=0, run_id=run_id,
                              mode="realtime", vehicles="external",
                              listen=(f"tcp/127.0.0.1:{port}",), log=lambda _line: None),
                 declare=declare)
    try:
        session = open_session(zenoh_config(mode="client",
                                            connect=[f"tcp/127.0.0.1:{port}"]))
        try:
            yield made, session
        finally:
            session.close()
    finally:
        made.close()


def test_running_is_published_at_the_start_then_every_clock_period(
        world: World, captured: CapturedPublishers, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(world_module.time, "monotonic", clock)

    def published() -> list[tuple[int, str]]:
        return [(c.step, c.state) for c in map(world.codec.decode_clock,
                                               captured[world.keys.clock].payloads)]

    for step in range(50):  # a fast lockstep: 50 steps within one clock period
        clock.now += CLOCK_PERIOD_S / 100
        world.publish_running(step)
    assert published() == [(0, "running")]
    clock.now += CLOCK_PERIOD_S
    world.publish_running(50)
    world.publish_running(51)
    assert published() == [(0, "running"), (50, "running")]
    assert captured[world.keys.clock].block  # lockstep peers wait for it: never dropped


def test_the_clock_reports_every_input_the_world_rejected(
        world: World, captured: CapturedPublishers) -> None:
    """The world has no telemetry of its own: its clock carries its rejection count."""
    fleet = world.fleet
    assert fleet is not None
    clock_payloads = captured[world.keys.clock].payloads
    world.publish_clock(0, "waiting")
    assert world.codec.decode_clock(clock_payloads[-1]).rejected_inputs == 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:
        for endpoint in fleet.endpoints:
            for datagram in (b"", b"\xfd\x03abc", b"\x00" * 40):
                junk.sendto(datagram, endpoint.local_address)
        wait_until(lambda: world.rejected_total() >= 3 * len(fleet.endpoints), 5.0,
                   "the vehicles to count three junk datagrams each",
                   between=lambda: fleet.service(0.1))
    total = world.rejected_total()
    world.publish_clock(0, "running")
    clock = world.codec.decode_clock(clock_payloads[-1])
    assert clock.state == "running" and clock.rejected_inputs == total


@pytest.mark.wallclock
def test_an_external_vehicle_world_counts_bad_beacons_on_its_clock() -> None:
    """With external vehicles the world subscribes to the beacons: junk there is counted and
    shows on its clock, and only a valid beacon moves a drone; the frame rendered from it
    carries the autopilot stamp of that position (the agent pairs the two)."""
    captured = CapturedPublishers()
    with external_world("extfuzz", captured) as (made, session):
        valid = made.codec.encode(BeaconWire.build(2, 5, 0.1, (1.0, 2.0, 3.0),
                                                   vehicle_time_ms=43_210))
        junk = [b"", b"\x93\x01\x02", valid[:-3], valid.replace(b"beacon", b"camera"),
                msgspec.msgpack.encode(["beacon", 3, 2, 5, 0.1, [math.nan, 2.0, 3.0],
                                        [0.0, 0.0, 0.0], 0.0]),
                # a valid beacon of drone 3 on drone 2's key
                made.codec.encode(BeaconWire.build(3, 5, 0.1, (9.0, 9.0, 9.0)))]
        for payload in [*junk, valid]:
            session.put(made.keys.beacon(2), payload)
        assert made.takes_beacons

        def all_taken() -> bool:
            made.take_beacons()  # what the realtime loop does at each tick
            return made.rejections.total() >= len(junk) and made.beacons.get(2) is not None

        wait_until(all_taken, 10.0, "the world to take the junk and the valid beacon")
        assert made.rejections.total() == len(junk)
        made.publish_clock(0, "waiting")
        clock_payloads = captured[made.keys.clock].payloads
        assert made.codec.decode_clock(clock_payloads[-1]).rejected_inputs == len(junk)
        made.place_external_drones()  # what the realtime loop does next
        assert made.positions[2].tolist() == [1.0, 2.0, 3.0]
        assert made.beacons.get(3) is None
        assert made.pose_stamps_ms == [0, 0, 43_210, 0, 0, 0]
        cameras = [captured[made.keys.camera(i)] for i in range(made.n)]
        made.publish_step(7, made.pose_stamps_ms)
        frames = [made.codec.decode_camera(c.payloads[-1]) for c in cameras]
        assert [f.vehicle_time_ms for f in frames] == [0, 0, 43_210, 0, 0, 0]
        assert {f.step for f in frames} == {7}
        # Stamped: a realtime agent sets the phase of its loop from when they left.
        assert all(c.stamped == [True] for c in cameras)


@pytest.mark.wallclock
def test_a_stalled_realtime_tick_counts_queued_setpoints_before_the_failsafe(
        world: World) -> None:
    """The world's loop stalls (a loaded machine) while the agent keeps streaming: the next
    tick takes the setpoints that queued up before it evaluates the setpoint-loss failsafe,
    so the vehicle flies them instead of failing safe."""
    import threading

    import numpy as np

    from swarm.mavlink.link import AutopilotLink

    assert world.fleet is not None
    vehicle = world.fleet.vehicles[0]
    link = AutopilotLink(f"udpin:127.0.0.1:{world.options.mavlink_base}", 0, "px4",
                         np.zeros(3), log=lambda _line: None)
    serving = threading.Event()
    serving.set()

    def serve() -> None:  # the world's MAVLink side while the agent shakes hands
        while serving.is_set():
            world.fleet.send_telemetry(world.boot_ms())
            world.fleet.service(0.01)

    server = threading.Thread(target=serve)
    server.start()
    try:
        link.handshake(timeout_s=20.0)
    finally:
        serving.clear()
        server.join()
    try:
        assert vehicle.in_setpoint_mode and vehicle.armed
        start = vehicle.position_w.copy()
        # The world's loop stalls for twice the failsafe time, the agent sending throughout
        # (the last setpoint just before the loop resumes).
        resume = time.monotonic() + 2 * vehicle.setpoint_timeout_s
        while time.monotonic() < resume:
            link.send_velocity(np.array([1.0, 0.0, 0.0]), 0)
            time.sleep(0.05)  # the agent's setpoint period; the stall is the point here
        world.move_vehicles(0)
        assert vehicle.failsafe_events == 0 and not vehicle.failsafe_active
        np.testing.assert_allclose(vehicle.position_w - start, [world.dt_s, 0.0, 0.0],
                                   atol=1e-6)
    finally:
        link.close()


@pytest.mark.wallclock
def test_a_realtime_world_relays_every_drones_newest_beacon_and_how_long_it_held_it() -> None:
    """At each realtime tick the agents get one message (world/beacons, stamped) with every
    drone's newest beacon, each with how long the world has held it: N messages a period
    through the router instead of N(N − 1)."""
    heard: list[tuple[bytes, bool]] = []
    with external_world("relay") as (made, session):
        session.declare_subscriber(made.keys.beacon_relay, lambda sample: heard.append(
            (sample.payload.to_bytes(), sample.timestamp is not None)))
        # Drone 1 twice (the newest counts), drone 4 once.
        for j, x in ((1, 1.0), (4, 4.0), (1, 1.5)):
            session.put(made.keys.beacon(j), made.codec.encode(
                BeaconWire.build(j, 5, 0.1, (x, 0.0, 3.0))))

        def both_in() -> bool:
            made.take_beacons()
            one = made.beacons.get(1)
            return (one is not None and one[0].position_m[0] == 1.5
                    and made.beacons.get(4) is not None)

        wait_until(both_in, 10.0, "drone 1's newest and drone 4's beacon at the world")
        relays = []
        for step in (9, 10):
            before = time.monotonic()
            made.relay_beacons(step)
            relays.append((before, time.monotonic()))
            time.sleep(0.05)  # the scenario, not a wait: the second relay's beacons are older
        wait_until(lambda: len(heard) >= 2, 10.0, "both relays at the subscriber")
        first, second = (made.codec.decode_beacon_relay(payload) for payload, _ in heard)
        assert all(stamped for _, stamped in heard)
        assert (first.step, second.step) == (9, 10)
        assert first.sender_ids().tolist() == [1, 4]
        assert first.rows()[:, RELAY_POSITION].tolist() == [[1.5, 0.0, 3.0], [4.0, 0.0, 3.0]]
        (start1, end1), (start2, end2) = relays
        for a, b in zip(first.rows()[:, RELAY_HELD], second.rows()[:, RELAY_HELD], strict=True):
            assert start2 - end1 <= b - a <= end2 - start1
        assert made.rejections.total() == 0


def test_a_lockstep_worlds_frames_carry_every_drones_reported_position(
        world: World, captured: CapturedPublishers) -> None:
    """Lockstep: every camera frame of step k carries each drone's position as its vehicle
    reports it in LOCAL_POSITION_NED then (what that drone's beacon of step k would carry);
    the world takes no beacon and publishes no relay, so nothing waits for N beacons."""
    fleet = world.fleet
    assert fleet is not None
    cameras = [captured[world.keys.camera(i)] for i in range(world.n)]
    reported = fleet.reported_positions_w()
    world.publish_step(3, [1060] * world.n, reported)
    for i, publisher in enumerate(cameras):
        (payload,) = publisher.payloads
        frame = world.codec.decode_camera(payload)
        assert (frame.drone, frame.step, frame.vehicle_time_ms) == (i, 3, 1060)
        positions = frame.drone_position_array()
        assert positions is not None
        np.testing.assert_array_equal(positions.view(np.uint64), reported.view(np.uint64))
    for i, vehicle in enumerate(fleet.vehicles):
        np.testing.assert_array_equal(reported[i], vehicle.reported_position_w)
    assert not world.takes_beacons and world.keys.beacon_relay not in captured.by_key
    published = captured.total()
    world.relay_beacons(3)
    assert captured.total() == published  # a lockstep world relays nothing
    world.publish_step(4, [1080] * world.n)  # no positions: frames without them
    assert world.codec.decode_camera(cameras[0].payloads[-1]).drone_positions is None
