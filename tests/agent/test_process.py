"""An agent process's Zenoh inputs: a message is taken only from the key of its sender, and
realtime beacons only from the world's relay.

A real ``AgentProcess`` (drone 0 of Case 1) joins a router in this process; another session
puts valid messages on the wrong keys (another drone's data, a beacon claiming to be drone
0): each is counted as rejected and never stored, while the same message on its own key is.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarm.agent.process import AgentOptions, AgentProcess
from swarm.core.drone_step import ConsensusMessage
from swarm.messages.wire import BeaconRelayWire, BeaconWire, CameraFrameWire
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.net.stores import LatestValues
from swarm.scenario.config import load_config
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.waiting import wait_until

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


def consensus(sender: int, m: int, n_state: int) -> ConsensusMessage:
    rng = np.random.default_rng(sender)
    return ConsensusMessage.of_arrays(sender, 3, 1, rng.normal(size=(m, n_state, n_state)),
                                      rng.normal(size=(m, n_state)))


@contextlib.contextmanager
def agent_on_a_router(mode: str, run_id: str) -> Iterator[tuple[AgentProcess, Any]]:
    """A real AgentProcess (drone 0 of Case 1, neighbours 1, 3, 5) on a router of this
    process, and the router's session to put messages with."""
    config = load_config(CASE1)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    agent = None
    try:
        agent = AgentProcess(AgentOptions(
            config=config, drone_id=0, seed=0, run_id=run_id, mavlink_url="udpin:127.0.0.1:0",
            connect=(endpoint,), mode=mode, log=lambda _line: None))
        assert agent.neighbours == {1, 3, 5}
        yield agent, router
    finally:
        if agent is not None:
            agent.close()
        router.close()


def taken(agent: AgentProcess, condition: Callable[[], bool]) -> bool:
    """Realtime samples wait in rings until the agent's loop takes them (Peers.drain);
    nothing runs that loop here, so the test takes them itself."""
    agent.exchange.peers.drain()
    return condition()


def test_messages_on_another_drones_key_are_counted_and_dropped() -> None:
    with agent_on_a_router("realtime", "keys") as (agent, router):
        keys, codec = Keys("keys"), agent.codec
        payload = codec.encode(consensus(1, 1, 6))

        # Our own publications reach the router once the subscriptions are declared: repeat
        # the valid message until it is in (zenoh declares routes asynchronously).
        def delivered() -> bool:
            router.put(keys.consensus(1), payload)
            return taken(agent, lambda: agent.exchange.consensus_latest.get((1, 1)) is not None)

        wait_until(delivered, 10.0, "drone 1's consensus message at the agent")
        router.put(keys.consensus(3), payload)  # drone 1's message on drone 3's key
        wait_until(lambda: taken(agent, lambda: agent.rejections.total() == 1), 10.0,
                   "the message on the wrong key counted")
        counts = agent.rejections.snapshot()
        assert counts["consensus"]["rejected"] == 1
        assert counts["consensus"]["rules"] == {"source": 1}
        assert set(agent.exchange.consensus_latest.ages()) == {(1, 1)}


def test_lockstep_positions_of_step_k_come_with_the_camera_frame_of_step_k() -> None:
    """A lockstep agent takes every other drone's position of step k from its camera frame of
    step k (what their vehicles report) and listens to no beacon: neither the world's relay
    nor any drone's beacon key."""
    with agent_on_a_router("lockstep", "lockrelay") as (agent, router):
        keys, codec = Keys("lockrelay"), agent.codec
        forged = codec.encode(BeaconWire.build(4, 1, 0.02, (9.0, 0.0, 3.0)))
        relay = codec.encode(BeaconRelayWire.build(1, (
            (BeaconWire.build(j, 1, 0.02, (9.0, 0.0, 3.0)), 0.0) for j in range(6))))
        positions = np.array([[float(j), 0.5 * j, 3.0] for j in range(6)])
        frame = codec.encode(CameraFrameWire.build(0, 1, 0.02, 1020, [],
                                                   drone_positions=positions))
        # Each frame leaves after a beacon on drone 4's key and a relay, on the same link:
        # had the agent listened to either, it would have them (and a relay in lockstep is
        # refused, which would count). The frame waits in the camera's FIFO until the agent
        # takes it (as before the mission, ``wait_first_frame``).
        def delivered() -> bool:
            router.put(keys.beacon(4), forged)
            router.put(keys.beacon_relay, relay)
            router.put(keys.camera(0), frame)
            agent.exchange.wait_first_frame(0.01)
            return agent.camera_latest.get(0) is not None

        wait_until(delivered, 10.0, "the camera frame at the agent")
        got = agent.exchange.beacons(1, 0.0, np.zeros(3))
        assert got == {
            j: positions[j].tolist() for j in range(1, 6)}  # not our own
        assert agent.rejections.total() == 0
        assert not agent.exchange.relayed_beacons


@pytest.mark.wallclock
def test_realtime_beacons_come_from_the_worlds_relay_dated_from_their_arrival_there() -> None:
    """A realtime agent takes the others' beacons from the world's relay (world/beacons),
    each dated from when it reached the world (the relay's arrival minus how long the world
    held it), and leaves out its own; a drone's own beacon key is not listened to."""
    with agent_on_a_router("realtime", "relay") as (agent, router):
        keys, codec = Keys("relay"), agent.codec
        relay = codec.encode(BeaconRelayWire.build(9, (
            (BeaconWire.build(j, 8, 0.16, (float(j), 0.0, 3.0)), held_s)
            for j, held_s in ((0, 0.0), (2, 0.004), (3, 5.0)))))

        def delivered() -> bool:
            router.put(keys.beacon_relay, relay)
            return taken(agent, lambda: 2 in agent.exchange.beacon_ages())

        wait_until(delivered, 10.0, "the world's relay at the agent")
        ages = agent.exchange.beacon_ages()
        assert set(ages) == {2, 3}  # not our own
        assert ages[3] >= 5.0 and ages[2] >= 0.004 and ages[3] - ages[2] == pytest.approx(
            5.0 - 0.004, abs=0.05)
        router.put(keys.beacon(4), codec.encode(BeaconWire.build(4, 8, 0.16, (4.0, 0.0, 3.0))))
        # The next relay leaves after that beacon on the same link: once it is in, the
        # beacon would be too, had the agent listened to drone 4's key.
        router.put(keys.beacon_relay, codec.encode(BeaconRelayWire.build(10, (
            (BeaconWire.build(1, 9, 0.18, (1.0, 0.0, 3.0)), 0.0),))))
        wait_until(lambda: taken(agent, lambda: 1 in agent.exchange.beacon_ages()), 10.0,
                   "the second relay at the agent")
        assert 4 not in agent.exchange.beacon_ages()
        assert agent.rejections.total() == 0


def test_realtime_reads_drain_only_the_rings_of_their_stream() -> None:
    """The inbox of a round drains the consensus rings, the beacons the relay's ring
    (``Peers.drain(stream)``); the loop's tick drains every ring."""
    with agent_on_a_router("realtime", "streams") as (agent, router):
        keys, codec, exchange = Keys("streams"), agent.codec, agent.exchange
        drain = exchange.peers.drain
        relay = codec.encode(BeaconRelayWire.build(9, (
            (BeaconWire.build(2, 8, 0.16, (2.0, 0.0, 3.0)), 0.0),)))
        message = codec.encode(consensus(1, 1, 6))

        def routed() -> bool:  # the subscriptions are declared at the router
            router.put(keys.beacon_relay, relay)
            router.put(keys.consensus(1), message)
            drain()
            return (2 in exchange.beacon_ages()
                    and exchange.consensus_latest.get((1, 1)) is not None)

        wait_until(routed, 10.0, "a relay and a consensus message at the agent")
        # One link, in order: once the later sample is taken, the earlier one is in its ring,
        # and only its own stream's drain takes it.
        def beacon() -> object:
            return exchange.beacon_ages().get(2)

        def round_1() -> object:
            return exchange.consensus_latest.get((1, 1))

        for (first_key, first, first_taken, first_stream), (later_key, later, later_taken,
                                                             later_stream) in (
                ((keys.beacon_relay, relay, beacon, "beacons"),
                 (keys.consensus(1), message, round_1, "consensus")),
                ((keys.consensus(1), message, round_1, "consensus"),
                 (keys.beacon_relay, relay, beacon, "beacons"))):
            exchange.relay, exchange.consensus_latest = None, LatestValues()
            router.put(first_key, first)
            router.put(later_key, later)
            wait_until(lambda s=later_stream, t=later_taken: (drain(s), t())[1] is not None,
                       10.0, f"the later sample taken by a drain of {later_stream}")
            assert first_taken() is None
            drain(first_stream)
            assert first_taken() is not None
