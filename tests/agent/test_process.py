"""An agent process's Zenoh inputs: a message is taken only from the key of its sender.

A real ``AgentProcess`` (drone 0 of Case 1) joins a router in this process; another session
puts valid messages on the wrong keys (another drone's data, a beacon claiming to be drone
0): each is counted as rejected and never stored, while the same message on its own key is.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from swarm.agent.process import AgentOptions, AgentProcess
from swarm.core.agent import ConsensusMessage
from swarm.messages.wire import BeaconWire
from swarm.net.transport import Keys, open_session, zenoh_config
from swarm.scenario.config import load_config
from tests.helpers.process_tools import free_tcp_port

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


def wait_until(condition, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)  # polling a condition with a deadline
    return True


def consensus(sender: int, m: int, n_state: int) -> ConsensusMessage:
    rng = np.random.default_rng(sender)
    return ConsensusMessage(sender, 3, 1, rng.normal(size=(m, n_state, n_state)),
                            rng.normal(size=(m, n_state)))


def test_messages_on_another_drones_key_are_counted_and_dropped() -> None:
    config = load_config(CASE1)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    agent = None
    try:
        agent = AgentProcess(AgentOptions(
            config=config, drone_id=0, seed=0, run_id="keys", mavlink_url="udpin:127.0.0.1:0",
            connect=(endpoint,), mode="realtime", log=lambda _line: None))
        assert agent.neighbours == {1, 3, 5}
        keys, codec = Keys("keys"), agent.codec
        wrong = [  # (key, payload)
            (keys.beacon(2), codec.encode(BeaconWire.build(3, 1, 0.02, (1.0, 0.0, 3.0)))),
            (keys.beacon(0), codec.encode(BeaconWire.build(0, 1, 0.02, (1.0, 0.0, 3.0)))),
            (keys.consensus(3), codec.encode(consensus(1, 1, 6))),
        ]
        right = [(keys.beacon(3), wrong[0][1]), (keys.consensus(1), wrong[2][1])]

        # Realtime samples wait in rings until the agent's loop takes them (Peers.drain);
        # nothing runs that loop here, so the test takes them itself.
        def taken(condition) -> bool:
            agent.exchange.peers.drain()
            return condition()

        # Our own publications reach the router once the subscriptions are declared: repeat
        # the valid beacon until it is in (zenoh declares routes asynchronously).
        def delivered() -> bool:
            router.put(*right[0])
            return taken(lambda: agent.exchange.beacon_latest.get(3) is not None)

        assert wait_until(delivered)
        for key, payload in wrong:
            router.put(key, payload)
        router.put(*right[1])
        assert wait_until(lambda: taken(
            lambda: agent.exchange.consensus_latest.get((1, 1)) is not None))
        assert wait_until(lambda: taken(lambda: agent.rejections.total() == len(wrong)))
        counts = agent.rejections.snapshot()
        assert counts["beacon"]["rejected"] == 2 and counts["consensus"]["rejected"] == 1
        assert counts["beacon"]["rules"] == {"source": 2}  # valid messages on the wrong key
        beacons = agent.exchange.beacon_latest
        assert beacons.get(0) is None and beacons.get(2) is None
        assert set(agent.exchange.consensus_latest.ages()) == {(1, 1)}
    finally:
        if agent is not None:
            agent.close()
        router.close()
