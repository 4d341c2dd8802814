"""The two exchanges of an agent's step (swarm.agent.exchange): what a step sees of the swarm
in lockstep and in realtime, on the real core and a real MAVLink link (no peers needed: the
messages are stored as the subscriptions store them, or in lockstep put on a Zenoh session
of the test into the exchange's own FIFOs; a settable clock ages them)."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle
from swarm.agent.exchange import (
    WAIT_SLICE_S,
    ExchangeError,
    LockstepExchange,
    Peers,
    RealtimeExchange,
    exchange_for,
    loop_phase_s,
)
from swarm.core import kernels
from swarm.core.drone_step import ConsensusMessage
from swarm.mavlink.link import AutopilotLink, LinkError
from swarm.messages.wire import BeaconRelayWire, BeaconWire, CameraFrameWire, WireCodec
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import RejectionCounter, subscribe
from swarm.scenario.config import load_config
from swarm.scenario.setup import build_agent

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"  # drone 0: {1, 3, 5}


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Ended(Exception):
    pass


@pytest.fixture
def link() -> Iterator[AutopilotLink]:
    config = load_config(CASE1)
    link = AutopilotLink("udpin:127.0.0.1:0", 0, "ardupilot", config.vehicles.origin_w(0))
    try:
        yield link
    finally:
        link.close()


def peers(link: AutopilotLink, *, ended: bool = False, drains: list[str | None] | None = None,
          **runtime: float) -> Peers:
    config = load_config(CASE1)
    config = dataclasses.replace(config, runtime=dataclasses.replace(config.runtime, **runtime))

    def check_clock() -> None:
        if ended:
            raise Ended

    lines: list[str] = []
    def drain(stream: str | None = None) -> None:  # the process's rings (DrainedSubscriber)
        if drains is not None:
            drains.append(stream)

    return Peers(0, set(config.swarm.graph.neighbours[0]), set(range(1, 6)), config,
                 build_agent(config, 0, 0), link, LatestValues(), check_clock, lines.append,
                 drain)


def message(sender: int, step: int, rnd: int) -> ConsensusMessage:
    """A valid message of (step, round) for one target; round 0 carries the states too."""
    states = {} if rnd else {"projector_mean": np.eye(3)[None], "weight_mean": np.ones(1),
                             "projector_integral": np.eye(3)[None],
                             "weight_integral": np.ones(1), "gramian": np.eye(3)[None]}
    return ConsensusMessage.of_arrays(sender, step, rnd, np.eye(6)[None], np.zeros((1, 6)),
                                      **states)


@contextlib.contextmanager
def subscribed(exchange: LockstepExchange
               ) -> Iterator[Callable[[ConsensusMessage | CameraFrameWire], None]]:
    """The exchange's camera and consensus subscriptions as the agent process makes them
    (``receiving``: a FIFO for the frames and one per neighbour) on a Zenoh session of this
    process, attached; yields how the world and the neighbours send (a put on that session,
    in the FIFO at once)."""
    session = open_session(zenoh_config(mode="peer"))
    keys, codec = Keys("exchange"), WireCodec(6, 1, 6)

    def on_camera(_key: str, frame: CameraFrameWire) -> None:  # as AgentProcess._on_camera
        exchange.put_camera(frame)
        exchange.peers.camera_latest.put(0, frame)

    camera = subscribe(session, keys.camera(0), codec.decode_camera, on_camera,
                       RejectionCounter(), "camera", **exchange.receiving("camera", 1))
    subs = {j: subscribe(session, keys.consensus(j), codec.decode_consensus,
                         lambda _key, msg: exchange.put_consensus(msg), RejectionCounter(),
                         "consensus", **exchange.receiving("consensus", 2))
            for j in sorted(exchange.peers.neighbours)}
    exchange.attach(camera, subs)

    def send(message: ConsensusMessage | CameraFrameWire) -> None:
        if isinstance(message, CameraFrameWire):
            session.put(keys.camera(message.drone), codec.encode(message))
        else:
            session.put(keys.consensus(message.sender), codec.encode(message))

    try:
        yield send
    finally:
        exchange.close()
        session.close()


def test_lockstep_waits_for_every_neighbour_of_the_round(link: AutopilotLink) -> None:
    """Each neighbour's messages come in order on its own FIFO; the inbox takes them until
    it has the round's, keeping any later one for its own inbox."""
    exchange = LockstepExchange(peers(link, lockstep_timeout_s=0.3))
    with subscribed(exchange) as send:
        for j in (1, 3, 5):
            send(message(j, 4, 0))
            send(message(j, 4, 1))
        send(message(1, 5, 0))  # the next step's, already there: kept for it
        assert {j: m.round for j, m in exchange.inbox(4, 0).items()} == {1: 0, 3: 0, 5: 0}
        inbox = exchange.inbox(4, 1)
        assert sorted(inbox) == [1, 3, 5] and all(m.round == 1 for m in inbox.values())
        started = time.monotonic()
        with pytest.raises(LinkError, match=r"drone 0: step 5: no round-0 consensus from "
                                            r"\[3, 5\] within 0.3 s"):
            exchange.inbox(5, 0)
        assert 0.3 <= time.monotonic() - started < 0.3 + 2 * WAIT_SLICE_S + 1.0
    with pytest.raises(ExchangeError, match="expected the neighbours \\[1, 3, 5\\]"):
        exchange.attach(exchange._camera_from[0], {})


def test_lockstep_inbox_needs_the_subscriptions_and_a_mission_end_ends_its_wait(
        link: AutopilotLink) -> None:
    """A wait on a neighbour that sends nothing ends when the exchange is closed (the world's
    "done" or "aborted"): at once, not at the deadline, and it says why."""
    with pytest.raises(ExchangeError, match="attach first"):
        LockstepExchange(peers(link)).inbox(0, 0)
    exchange = LockstepExchange(peers(link, ended=True))  # the clock said "done"
    with subscribed(exchange):
        closer = threading.Timer(0.2, exchange.close)
        started = time.monotonic()
        closer.start()
        with pytest.raises(Ended):
            exchange.inbox(0, 0)
        assert time.monotonic() - started < 5.0  # the deadline is the config's 20 s
    exchange = LockstepExchange(peers(link))  # closed without a mission end: said so
    with subscribed(exchange):
        exchange.close()
        with pytest.raises(LinkError, match="the exchange closed while waiting for round-1 "
                                            r"consensus from \[1, 3, 5\]"):
            exchange.inbox(0, 1)


def frame(step: int, positions: np.ndarray | None) -> CameraFrameWire:
    return CameraFrameWire.build(0, step, 0.02 * step, 1000 + 20 * step, [],
                                 drone_positions=positions)


def test_lockstep_beacons_are_the_frames_positions_taken_from_the_cameras_fifo(
        link: AutopilotLink) -> None:
    """The frames come through the camera's FIFO in order: the step takes its own and keeps
    a later one; the other drones' positions are the frame's; a frame that does not come
    ends the wait at the deadline. Before the mission the FIFO is looked at in turns."""
    exchange = LockstepExchange(peers(link, lockstep_timeout_s=0.3))
    positions = np.array([[float(j), 0.0, 3.0] for j in range(6)])
    with pytest.raises(ExchangeError, match="attach first"):
        exchange.beacons(7, 0.5, np.ones(3))
    with subscribed(exchange) as send:
        exchange.wait_first_frame(0.05)  # nothing yet: returns at its timeout
        assert exchange.peers.camera_latest.get(0) is None
        send(frame(7, positions))
        send(frame(8, positions + 1.0))  # the next step's: not these
        exchange.wait_first_frame(5.0)
        assert exchange.peers.camera_latest.get(0)[0].step in (7, 8)
        beacons = exchange.beacons(7, 0.5, np.ones(3))
        assert beacons == {  # lists of floats: the core takes them as they are
            j: [float(j), 0.0, 3.0] for j in range(1, 6)}  # the step's, not carried on
        assert exchange.beacons(8, 0.5, np.ones(3))[1] == [2.0, 1.0, 4.0]
        send(frame(9, None))
        with pytest.raises(LinkError, match=r"drone 0: step 9: the camera frame carries no "
                                            r"drone positions"):
            exchange.beacons(9, 0.0, np.ones(3))
        with pytest.raises(LinkError, match=r"step 10: no camera frame from \[0\] within 0.3 s"):
            exchange.beacons(10, 0.0, np.ones(3))
    with pytest.raises(ExchangeError, match="from its camera frame, not from a relay"):
        exchange.put_relay(BeaconRelayWire.build(7, [(BeaconWire.build(1, 7, 0.14,
                                                                    (1.0, 0.0, 3.0)), 0.0)]))
    assert exchange.setpoint_interval_s() == 0.02 == exchange.setpoint_interval_s()


def test_realtime_leaves_out_stale_messages_and_counts_them(link: AutopilotLink) -> None:
    exchange = RealtimeExchange(peers(link, stale_timeout_s=0.1))
    exchange.consensus_latest = LatestValues(clock=(clock := Clock()))
    exchange.put_consensus(message(1, 9, 0))
    clock.now += 0.05
    exchange.put_consensus(message(3, 12, 0))  # the newest of each sender, whatever its step
    clock.now += 0.06
    inbox = exchange.inbox(12, 0)
    assert sorted(inbox) == [3] and exchange.stale_messages == 1
    assert exchange.neighbour_age_ms == pytest.approx(60.0)
    assert exchange.inbox(12, 1) == {} and np.isnan(exchange.neighbour_age_ms)


def test_realtime_beacons_are_carried_forward_at_most_the_failsafe_time(
        link: AutopilotLink) -> None:
    exchange = RealtimeExchange(peers(link), clock=(clock := Clock()))
    hold_s = load_config(CASE1).vehicles.failsafe_timeout_s
    exchange.put_relay(BeaconRelayWire.build(3, [
        (BeaconWire.build(2, 3, 0.06, (1.0, 2.0, 3.0), velocity_m_s=(1, 0, 0),
                          sample_age_s=0.01), 0.0),
        (BeaconWire.build(4, 3, 0.06, (0.0, 0.0, 3.0), velocity_m_s=(0, 2, 0),
                          sample_age_s=hold_s), 0.0)]))
    clock.now += 0.03
    flying = np.array([0.0, 0.0, 1.0])
    beacons = exchange.beacons(5, 0.02, flying)
    np.testing.assert_allclose(beacons[2], [1.0 + 0.04, 2.0, 3.0 - 0.02])  # p + v·a − v_i·a_i
    np.testing.assert_allclose(beacons[4], [0.0, 2 * hold_s, 3.0 - 0.02])  # held after


def test_realtime_beacons_are_each_beacons_formula_to_the_bit(link: AutopilotLink) -> None:
    """``beacons`` carries all N − 1 forward in one array operation: each row equals
    p_j + min(a_j + age_j, hold)·v_j − a_i·v_i computed for that beacon alone, bit for bit
    (random swarms, ages on both sides of the failsafe hold; age_j = the relay's age + how
    long the world held beacon j)."""
    rng = np.random.default_rng(7)
    hold_s = load_config(CASE1).vehicles.failsafe_timeout_s
    for _ in range(50):
        exchange = RealtimeExchange(peers(link), clock=(clock := Clock()))
        n = int(rng.integers(1, 30))
        sent = [BeaconWire.build(j, 3, 0.06, tuple(rng.normal(0, 10, 3)),
                                 velocity_m_s=tuple(rng.normal(0, 2, 3)),
                                 sample_age_s=float(rng.uniform(0, 2 * hold_s)))
                for j in range(1, n + 1)]
        held = [float(rng.uniform(0, hold_s)) for _ in sent]
        arrived_s = clock.now - float(rng.uniform(0, 0.02))
        exchange.put_relay(BeaconRelayWire.build(3, zip(sent, held, strict=True)), arrived_s)
        clock.now += float(rng.uniform(0, 0.1))
        sample_age_s, flying = float(rng.uniform(0, 0.05)), rng.normal(0, 2, 3)
        beacons = exchange.beacons(5, sample_age_s, flying)
        assert sorted(beacons) == [b.sender for b in sent]
        for b, held_s in zip(sent, held, strict=True):
            lead = min(b.sample_age_s + ((clock.now - arrived_s) + held_s), hold_s)
            alone = (np.asarray(b.position_m, dtype=float)
                     + lead * np.asarray(b.velocity_m_s, dtype=float) - sample_age_s * flying)
            assert beacons[b.sender] == alone.tolist()  # bit for bit


def test_realtime_reads_take_the_rings_first_and_date_beacons_from_their_arrival(
        link: AutopilotLink) -> None:
    """Realtime samples wait in rings until the loop reads (``Peers.drain``), each read
    taking its own stream's rings: a beacon taken from its ring 15 ms after it arrived is
    carried forward from its arrival, not from when it was taken."""
    drains: list[str | None] = []
    exchange = RealtimeExchange(peers(link, drains=drains), clock=(clock := Clock()))
    clock.now = 10.0
    exchange.put_relay(BeaconRelayWire.build(3, [  # the world had held drone 2's 15 ms
        (BeaconWire.build(2, 3, 0.06, (1.0, 2.0, 3.0), velocity_m_s=(1, 0, 0)), 0.015),
        (BeaconWire.build(3, 3, 0.06, (5.0, 2.0, 3.0), velocity_m_s=(1, 0, 0)), 0.0)]))
    clock.now += 0.005
    beacons = exchange.beacons(4, 0.0, np.zeros(3))
    np.testing.assert_allclose(beacons[2], [1.0 + 0.020, 2.0, 3.0])
    np.testing.assert_allclose(beacons[3], [5.0 + 0.005, 2.0, 3.0])
    assert drains == ["beacons"]
    exchange.inbox(4, 0)
    assert drains == ["beacons", "consensus"]
    # An arrival stamped after now (a skewed clock) counts as now: no negative age.
    exchange.put_relay(BeaconRelayWire.build(4, [(BeaconWire.build(
        2, 4, 0.08, (1.0, 2.0, 3.0), velocity_m_s=(1, 0, 0)), 0.0)]), clock.now + 1.0)
    np.testing.assert_allclose(exchange.beacons(5, 0.0, np.zeros(3))[2], [1.0, 2.0, 3.0])


def test_realtime_swarm_size_follows_the_drones_heard(link: AutopilotLink) -> None:
    p = peers(link, member_timeout_s=1.0)
    exchange = RealtimeExchange(p, clock=(clock := Clock()))
    exchange.put_relay(BeaconRelayWire.build(0, [(BeaconWire.build(j, 0, 0.0, (j, 0.0, 3.0)),
                                                  0.0) for j in range(1, 6)]))
    exchange.begin(0)
    assert exchange.members == frozenset(range(6)) and p.agent.swarm_size == 6
    clock.now += 0.5
    exchange.put_relay(BeaconRelayWire.build(25, [(BeaconWire.build(j, 25, 0.5, (j, 0.0, 3.0)),
                                                   0.0) for j in (1, 2, 3)]))
    clock.now += 0.7  # 4 and 5 last heard 1.2 s ago
    exchange.begin(60)
    assert exchange.members == frozenset({0, 1, 2, 3}) and p.agent.swarm_size == 4


@given(st.integers(1, 64), st.floats(1e-3, 1.0))
def test_the_loops_spread_evenly_over_the_period_none_at_the_worlds_tick(
        n_drones: int, period_s: float) -> None:
    phases = [loop_phase_s(i, n_drones, period_s) for i in range(n_drones)]
    gap = period_s / (n_drones + 1)
    assert phases[0] == pytest.approx(gap) and period_s - phases[-1] == pytest.approx(gap)
    assert np.allclose(np.diff(phases), gap)


@pytest.mark.wallclock
def test_realtime_loop_ticks_at_its_phase_after_the_first_frame_left_the_world(
        link: AutopilotLink) -> None:
    """The first step runs ``loop_phase_s`` after the first frame was put (its arrival, as
    the ring dates it from its stamp), each next one a period later: drone 5 of 6 ticks
    6/7 of a period after the world, not as soon as it sees the frame."""
    p = dataclasses.replace(peers(link), drone_id=5)
    config = p.config
    assert link.local_address is not None
    # PX4 streams LOCAL_POSITION_NED unasked; the link reads samples whatever its flavour.
    vehicle = EmulatedVehicle(0, "px4", (0.0, 0.0, 3.0), config.vehicles.origin_w(0))
    endpoint = VehicleEndpoint(("127.0.0.1", link.local_address[1]))
    try:
        endpoint.send(vehicle.telemetry(1000, 1.0))
        deadline = time.monotonic() + 3.0
        while link.latest_position() is None:
            assert time.monotonic() < deadline, "no position sample reached the link"
            time.sleep(0.005)
        put_s = time.monotonic()
        p.camera_latest.put(0, CameraFrameWire.build(5, 7, 0.14, 1000, []), arrived_s=put_s)
        ticks: list[tuple[int, float]] = []

        def step(k: int, *_: object) -> None:
            ticks.append((k, time.monotonic()))
            if len(ticks) == 4:
                raise Ended

        with pytest.raises(Ended):
            RealtimeExchange(p).run(step)
    finally:
        endpoint.close()
    period = config.scenario.dt_s
    phase = loop_phase_s(5, 6, period)
    assert phase == pytest.approx(6 / 7 * period)
    assert [k for k, _ in ticks] == [7, 8, 9, 10]  # counted from the frame's step
    for i, (_, at) in enumerate(ticks):
        assert at >= put_s + phase + i * period


def test_an_unknown_mode_is_refused(link: AutopilotLink) -> None:
    assert isinstance(exchange_for("realtime", peers(link)), RealtimeExchange)
    with pytest.raises(ExchangeError, match="unknown mode 'warp'"):
        exchange_for("warp", peers(link))


def test_realtime_keeps_the_newest_relay_whole_without_its_own_beacon(
        link: AutopilotLink) -> None:
    """A relay replaces the one held (it carries every drone the world has heard), unless it
    is older; our own beacon, which comes back with everyone's, is left out."""
    exchange = RealtimeExchange(peers(link), clock=(clock := Clock()))

    def relay(step: int, held: dict[int, float]) -> BeaconRelayWire:
        return BeaconRelayWire.build(step, [(BeaconWire.build(j, step, 0.0, (j, 0.0, 3.0)), h)
                                            for j, h in held.items()])

    exchange.put_relay(relay(5, {0: 0.0, 1: 0.25, 2: 0.5}))
    assert exchange.beacon_ages() == {1: 0.25, 2: 0.5}
    exchange.put_relay(relay(4, {3: 0.0}))  # older: not taken
    clock.now += 0.5
    assert exchange.beacon_ages() == {1: 0.75, 2: 1.0}
    exchange.put_relay(relay(6, {1: 0.0}), arrived_s=clock.now - 0.125)
    assert exchange.beacon_ages() == {1: 0.125}


def test_realtime_members_are_the_drones_the_world_heard_recently(link: AutopilotLink) -> None:
    """The relay carries every drone the world has heard, with how long it held each beacon:
    N counts those heard within ``member_timeout_s`` (and, until that long after our first
    step, those not heard at all yet)."""
    p = peers(link, member_timeout_s=1.0)
    exchange = RealtimeExchange(p, clock=(clock := Clock()))
    exchange.put_relay(BeaconRelayWire.build(0, [
        (BeaconWire.build(j, 0, 0.0, (j, 0.0, 3.0)), held) for j, held in
        ((1, 0.0), (2, 0.9), (3, 1.5))]))
    exchange.begin(0)  # 3: held too long; 4 and 5: never heard, the mission just started
    assert exchange.members == frozenset({0, 1, 2, 4, 5}) and p.agent.swarm_size == 5
    clock.now += 0.2  # 2 held 1.1 s by now
    exchange.begin(10)
    assert exchange.members == frozenset({0, 1, 4, 5})
    clock.now += 0.9  # past the start-up allowance: the never-heard are out
    exchange.put_relay(BeaconRelayWire.build(55, [
        (BeaconWire.build(j, 55, 1.1, (j, 0.0, 3.0)), 0.0) for j in (1, 3)]))
    exchange.begin(55)
    assert exchange.members == frozenset({0, 1, 3}) and p.agent.swarm_size == 3


def _positions_around(rng: np.random.Generator, n: int, own: np.ndarray,
                      radius_m: float) -> np.ndarray:
    """N positions: some inside R_ca, some just outside it and outside the margin, some at
    exactly R_ca, one not finite."""
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    distance = rng.choice([0.3 * radius_m, radius_m, 1.05 * radius_m, 1.5 * radius_m,
                           4.0 * radius_m], size=n)
    positions = own + distance[:, None] * directions
    positions[rng.integers(n)] = [np.nan, 0.0, 3.0]
    return positions


def test_around_a_position_the_core_gets_every_drone_it_uses_and_no_more_work(
        link: AutopilotLink) -> None:
    """``beacons(..., around=p)`` in both exchanges: the QP rows the core builds from it
    (``kernels.qp_rows``, the agent's own call) are those it builds from every drone, bit for
    bit; the graph neighbours are there wherever they are (formation bearings), a position
    that is not finite too (the core counts it rejected); and drones beyond R_ca + margin are
    left out."""
    rng = np.random.default_rng(11)
    config = load_config(CASE1)
    ctrl = config.control
    radius = ctrl.collision_radius_m
    constants = kernels.qp_row_constants({
        "n_agents": 6.0, "gamma": ctrl.gamma, "collision_radius_m": radius,
        "collision_distance_m": ctrl.collision_distance_m, "collision_gain": ctrl.collision_gain,
        "tracking_error_bound_m_s": 0.1,
        "localization_share": kernels.LOCALIZATION_SHARES["equal"]})
    neighbours = set(config.swarm.graph.neighbours[0])

    def qp_rows(beacons: dict[int, list[float]], own: np.ndarray
                ) -> tuple[list[float], list[float]]:  # as DroneAgent._qp_rows calls it
        others = [beacons[j] for j in sorted(beacons)]
        return kernels.qp_rows(np.zeros((1, kernels.ROW_SIZE)), np.zeros((1, 3)), [1.0],
                               own.tolist(), others, [], [], constants)

    left_out = 0
    for case in range(200):
        own = rng.normal(0.0, 3.0, 3)
        positions = _positions_around(rng, 6, own, radius)
        if case % 2:
            exchange: LockstepExchange | RealtimeExchange = LockstepExchange(peers(link))
            exchange.put_camera(frame(3, positions))
        else:
            exchange = RealtimeExchange(peers(link), clock=Clock())
            exchange.put_relay(BeaconRelayWire.build(3, [  # no codec: NaN stays
                (BeaconWire.build(j, 3, 0.06, tuple(positions[j])), 0.0) for j in range(6)]))
        flying = np.zeros(3)
        every = exchange.beacons(3, 0.0, flying)
        near = exchange.beacons(3, 0.0, flying, around=own)
        assert set(near) <= set(every) and neighbours <= set(near)
        for j in near:  # NaN included
            np.testing.assert_array_equal(near[j], every[j])
        assert {j for j in every if not np.isfinite(every[j]).all()} <= set(near)
        for j in set(every) - set(near):
            assert np.linalg.norm(np.subtract(every[j], own)) > radius + 0.5 - 1e-9
        left_out += len(every) - len(near)
        assert qp_rows(near, own) == qp_rows(every, own)
    assert left_out > 100  # the cases did leave drones out
