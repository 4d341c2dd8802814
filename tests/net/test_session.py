"""Zenoh sessions (swarm.net.session): configs, opening, publishing, and real sessions in real
processes on loopback.

No sleeps hide races: cross-process checks wait for the child's report with a deadline, and a
publish is repeated until it is seen (route establishment is asynchronous in Zenoh).
"""

from __future__ import annotations

import json
import os
import queue
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from swarm.messages.wire import WIRE_VERSION, BeaconWire
from swarm.net.keys import Keys
from swarm.net.session import (
    ZENOH_RUNTIME_DEFAULT,
    TransportError,
    declare_publisher,
    is_loopback_endpoint,
    open_session,
    parse_endpoint,
    put_stamped,
    zenoh_config,
)
from swarm.net.stores import StepMailbox
from swarm.net.subscriptions import RejectionCounter, subscribe
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.zenoh_tools import (
    CODEC,
    DEADLINE_S,
    ROOT,
    Child,
    assert_loopback_only,
    endpoint,
    inet_sockets,
    iter_queue,
    repeat_until,
    session,
)


def config_value(config: zenoh.Config, key: str):
    return json.loads(config.get_json(key))


def test_config_is_explicit_and_loopback_only() -> None:
    config = zenoh_config(mode="router", listen=[endpoint(7447)], connect=["tcp/[::1]:7448"])
    assert config_value(config, "mode") == "router"
    assert config_value(config, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert config_value(config, "connect/endpoints") == ["tcp/[::1]:7448"]
    assert config_value(config, "scouting/multicast/enabled") is False
    assert config_value(config, "scouting/gossip/enabled") is True
    assert config_value(config, "transport/shared_memory/enabled") is False
    default = zenoh_config()
    assert config_value(default, "mode") == "peer"
    assert config_value(default, "listen/endpoints") == []  # not zenoh's tcp/[::]:0
    assert config_value(default, "connect/endpoints") == []
    client = zenoh_config(mode="client", connect=[endpoint(1)], connect_timeout_s=2.5)
    assert config_value(client, "scouting/gossip/enabled") is False
    assert config_value(client, "connect/timeout_ms") == 2500
    assert config_value(client, "connect/exit_on_failure") is True


@pytest.mark.parametrize("bad", [
    "tcp/127.0.0.1", "127.0.0.1:7447", "tcp://127.0.0.1:7447", "quic/127.0.0.1:7447",
    "tcp/127.0.0.1:99999", "tcp/127.0.0.1:0", "tcp/300.1.1.1:7447", "tcp/[::zz]:7447",
    "tcp/bad host:7447", "tcp/:7447", "tcp/127.0.0.1:74a7", "", "tcp/127.0.0.1:7447\nx",
])
def test_malformed_endpoints_are_one_line_value_errors(bad: str) -> None:
    with pytest.raises(ValueError) as info:
        zenoh_config(connect=[bad])
    assert "\n" not in str(info.value) and "endpoint" in str(info.value)


def test_endpoint_helpers_and_other_arguments() -> None:
    assert parse_endpoint("tcp/localhost:7447") == ("tcp", "localhost", 7447)
    assert parse_endpoint("udp/[::1]:0", role="listen") == ("udp", "[::1]", 0)
    assert zenoh_config(listen=["tcp/127.0.0.1:0"])  # any free port, loopback only
    assert is_loopback_endpoint("tcp/127.3.2.1:1") and is_loopback_endpoint("tcp/[::1]:1")
    assert is_loopback_endpoint("tcp/localhost:1")
    assert not is_loopback_endpoint("tcp/10.0.0.1:1") and not is_loopback_endpoint("tcp/a.b:1")
    with pytest.raises(ValueError, match="mode"):
        zenoh_config(mode="broker")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sequences"):
        zenoh_config(connect="tcp/127.0.0.1:7447")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="connect_timeout_s"):
        zenoh_config(connect_timeout_s=0)


def test_open_session_errors_are_one_line() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(TransportError, match="Address already in use") as info:
            open_session(zenoh_config(mode="router", listen=[endpoint(busy.getsockname()[1])]))
        assert "\n" not in str(info.value) and ".rs:" not in str(info.value)
    with pytest.raises(TransportError, match="Unable to connect"):
        open_session(zenoh_config(mode="client", connect=[endpoint(free_tcp_port())]))


def test_router_and_client_processes_exchange_validated_messages(spawn) -> None:
    port = free_tcp_port()
    router = spawn("--mode", "router", "--listen", endpoint(port), "--run-id", "alpha")
    keys = Keys("alpha")
    consensus: StepMailbox = StepMailbox()
    rejections = RejectionCounter()
    with session(zenoh_config(mode="client", connect=[endpoint(port)])) as client:
        subscribe(client, keys.all_consensus, CODEC.decode_consensus,
                  lambda key, m: consensus.put(m.step, m.round, m.sender, m), rejections,
                  "consensus")
        beacon_pub = declare_publisher(client, keys.beacon(2))

        # client → router (another process): a beacon, decoded and validated there.
        payload = CODEC.encode(BeaconWire.build(2, 5, 0.1, [-0.0, 1.5, 3.0]))
        got = repeat_until(lambda: beacon_pub.put(payload), lambda wait_s: router.next_event(
            lambda e: e["event"] == "value" and e["kind"] == "beacon" and e["step"] == 5, wait_s))
        assert got["key"] == keys.beacon(2) and got["sender"] == 2
        assert got["position"] == [-0.0, 1.5, 3.0] and str(got["position"][0]) == "-0.0"

        # A malformed payload on the key is counted and dropped; the next valid one arrives.
        beacon_pub.put(b"\x93garbage")
        beacon_pub.put(CODEC.encode(BeaconWire.build(2, 6, 0.12, [0.0, 0.0, 1.0])))
        got = router.expect(lambda e: e["event"] == "value" and e["step"] == 6, "beacon 6")
        assert got["rejections"]["beacon"]["rejected"] == 1
        assert "malformed beacon" in got["rejections"]["beacon"]["last_reason"]
        client.put(keys.beacon(1), CODEC.encode(BeaconWire.build(1, 7, 0.14, [0.0, 0.0, 1.0]))[:-3])
        client.put(keys.beacon(1), b"\x00" * 100)
        client.put(keys.beacon(1), CODEC.encode(BeaconWire.build(3, 8, 0.16, [0, 0, 1.0])))
        got = router.expect(lambda e: e["event"] == "value" and e["step"] == 8, "beacon 8")
        assert got["rejections"]["beacon"]["rejected"] == 3

        # router → client: consensus messages of several senders, gathered per (step, round).
        def publish_round() -> None:
            for sender in (1, 3, 5):
                router.send(cmd="consensus", sender=sender, step=4, round=0)

        found = repeat_until(publish_round, lambda wait_s: len(consensus.wait_for(
            4, 0, {1, 3, 5}, timeout_s=wait_s)) == 3)
        assert found
        inbox = consensus.wait_for(4, 0, {3, 5}, timeout_s=1.0)
        assert set(inbox) == {3, 5}
        assert np.all(inbox[3].information == 3004.0) and inbox[5].gramian.shape == (2, 3, 3)
        assert consensus.wait_for(4, 1, {1}, timeout_s=0.1) == {}  # nobody sent round 1

        # A wrong-version payload from the router is counted in this process, with the reason.
        bad = CODEC.encode(BeaconWire.build(0, 0, 0.0, [0, 0, 0])).replace(
            b"\xa6beacon" + bytes([WIRE_VERSION]), b"\xa6beacon" + bytes([WIRE_VERSION + 1]))
        router.send(cmd="raw", key=keys.beacon(0), hex=bad.hex())
        rejects = RejectionCounter()
        subscribe(client, keys.beacon(0), CODEC.decode_beacon, lambda k, v: None, rejects,
                  "beacon")
        repeat_until(lambda: router.send(cmd="raw", key=keys.beacon(0), hex=bad.hex()),
                     lambda wait_s: rejects.wait_for_total(1, wait_s))
        assert f"version {WIRE_VERSION + 1}" in rejects.snapshot()["beacon"]["last_reason"]

        # Nothing outside loopback: the router's sockets are loopback TCP only, no UDP at all.
        assert_loopback_only(router.ready["pid"])
        assert any(port == p for _, _, p in inet_sockets(router.ready["pid"]))
    assert rejections.total() == 0


def test_stamped_puts_tell_the_receiver_when_the_data_left() -> None:
    """``put_stamped`` carries the sender's time of the put; ``on_sent_time`` gets it before
    ``on_value`` (between the put and the arrival); an unstamped put calls only
    ``on_value``."""
    port = free_tcp_port()
    keys = Keys("stamp")
    events: queue.Queue = queue.Queue()

    def on_value(_key: str, beacon) -> None:
        events.put(("value", beacon.step, time.time()))

    def on_sent(beacon, unix_s: float) -> None:
        events.put(("sent", beacon.step, unix_s))

    # Peers (a router would stamp unstamped samples itself, with its own clock).
    with session(zenoh_config(mode="peer", listen=[endpoint(port)])) as hub, \
            session(zenoh_config(mode="peer", connect=[endpoint(port)])) as client:
        subscribe(hub, keys.all_beacons, CODEC.decode_beacon, on_value, RejectionCounter(),
                  "beacon", on_sent_time=on_sent)
        publisher = declare_publisher(client, keys.beacon(2))
        step = 0

        def put() -> None:
            nonlocal step
            step += 1
            payload = CODEC.encode(BeaconWire.build(2, step, 0.0, [0, 0, 1.0]))
            events.put(("put", step, time.time()))
            put_stamped(client, publisher, payload)

        repeat_until(put, lambda wait_s: any(
            e[0] == "value" for e in iter_queue(events, wait_s)) or None)
        put()
        stamped = step
        publisher.put(CODEC.encode(BeaconWire.build(2, step + 1, 0.0, [0, 0, 1.0])))  # unstamped
        seen: list[tuple[str, int, float]] = []
        while ("value", stamped + 1) not in [(kind, k) for kind, k, _t in seen]:
            event = events.get(timeout=DEADLINE_S)
            if event[1] >= stamped:  # warm-up puts may still be arriving
                seen.append(event)
    kinds = [(kind, k) for kind, k, _t in seen]
    assert kinds == [("put", stamped), ("sent", stamped), ("value", stamped),
                     ("value", stamped + 1)], kinds
    put_s, sent_s, arrived_s = seen[0][2], seen[1][2], seen[2][2]
    assert put_s - 0.005 <= sent_s <= arrived_s + 0.005


def test_two_swarms_at_once_never_see_each_other(spawn) -> None:
    """Swarm A: router + client; swarm B: peer + peer. Different run ids and ports."""
    port_a, port_b = free_tcp_port(), free_tcp_port()
    hub_a = spawn("--mode", "router", "--listen", endpoint(port_a), "--run-id", "swarmA")
    hub_b = spawn("--mode", "peer", "--listen", endpoint(port_b), "--run-id", "swarmB")
    member_a = spawn("--mode", "client", "--connect", endpoint(port_a), "--run-id", "swarmA")
    member_b = spawn("--mode", "peer", "--connect", endpoint(port_b), "--run-id", "swarmB")

    def exchange(sender: Child, receiver: Child, drone: int, step: int) -> None:
        repeat_until(lambda: sender.send(cmd="beacon", sender=drone, step=step),
                     lambda wait_s: receiver.next_event(
                         lambda e: e["event"] == "value" and e["sender"] == drone
                         and e["step"] == step, wait_s))

    # Both swarms busy at the same time, both directions, the same drone ids and keys
    # below the run id.
    for step in range(3):
        exchange(member_a, hub_a, 1, step)
        exchange(member_b, hub_b, 1, step)
        exchange(hub_a, member_a, 2, step)
        exchange(hub_b, member_b, 2, step)
    for child, run, other in ((hub_a, "swarmA", "swarmB"), (member_a, "swarmA", "swarmB"),
                              (hub_b, "swarmB", "swarmA"), (member_b, "swarmB", "swarmA")):
        stats = child.stats()
        assert set(stats["runs_seen"]) == {run}, stats  # vigil/** saw no other run at all
        assert stats["rejections"] == {}
        values = [e for e in child.seen if e["event"] == "value"]
        assert values and all(e["key"].startswith(f"vigil/{run}/") for e in values)
        assert not any(other in e["key"] for e in values)
    for child in (hub_a, hub_b, member_a, member_b):
        assert_loopback_only(child.ready["pid"])


# A router and a client in one fresh process exchange messages; then the zenoh threads alive
# are listed by name (their pools: app, tx, rx, acc, net), numbers dropped.
THREADS_SCRIPT = """
import json, os, sys, time
from swarm.net.session import declare_publisher, open_session, zenoh_config
from swarm.net.subscriptions import RejectionCounter, subscribe
endpoint = sys.argv[1]
router = open_session(zenoh_config(mode="router", listen=[endpoint]))
client = open_session(zenoh_config(mode="client", connect=[endpoint]))
got = []
sub = subscribe(client, "t/x", bytes, lambda _key, value, arrived_s=None: got.append(value),
                RejectionCounter(), "t", direct=True)
publisher = declare_publisher(router, "t/x")
deadline = time.monotonic() + 10
while not got and time.monotonic() < deadline:
    publisher.put(b"x")
    time.sleep(0.01)
names = {open(f"/proc/self/task/{t}/comm").read().strip().rstrip("0123456789-")
         for t in os.listdir("/proc/self/task")}
print(json.dumps({"delivered": bool(got), "pools": sorted(names & {"app", "tx", "rx", "acc",
                                                                     "net"}),
                  "setting": os.environ.get("ZENOH_RUNTIME")}))
"""


def zenoh_pools(runtime: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if runtime is not None:
        env["ZENOH_RUNTIME"] = runtime
    done = subprocess.run([sys.executable, "-c", THREADS_SCRIPT, endpoint(free_tcp_port())],
                          capture_output=True, text=True, timeout=60, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def test_zenoh_receives_on_its_app_thread_and_transmits_on_its_own() -> None:
    """open_session's default thread pools (session.ZENOH_RUNTIME_DEFAULT): receiving,
    accepting and link management on zenoh's one app thread, transmission on a thread of its
    own; messages still flow."""
    report = zenoh_pools(None)
    assert report["delivered"]
    assert report["pools"] == ["app", "tx"]
    assert report["setting"] == ZENOH_RUNTIME_DEFAULT


def test_a_users_own_zenoh_runtime_setting_wins() -> None:
    report = zenoh_pools("(rx: (worker_threads: 2))")
    assert report["delivered"]
    assert {"rx", "tx", "app"} <= set(report["pools"])
    assert report["setting"] == "(rx: (worker_threads: 2))"
