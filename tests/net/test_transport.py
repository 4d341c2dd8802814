"""Zenoh transport: configs, keys, stores, and real sessions in real processes on loopback.

No sleeps hide races: cross-process checks wait for the child's report with a deadline, and a
publish is repeated until it is seen (route establishment is asynchronous in Zenoh).
"""

from __future__ import annotations

import contextlib
import ipaddress
import itertools
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from swarm.messages.wire import WIRE_VERSION, BeaconWire, WireCodec
from swarm.net.transport import (
    KEY_ROOT,
    ZENOH_RUNTIME_DEFAULT,
    BlockingReceives,
    DrainedSubscriber,
    FaultyPublisher,
    Keys,
    LatestValues,
    LinkFaults,
    RejectionCounter,
    StepMailbox,
    TransportError,
    declare_publisher,
    is_loopback_endpoint,
    open_session,
    parse_endpoint,
    put_stamped,
    subscribe,
    zenoh_config,
)
from tests.helpers.process_tools import free_tcp_port

ROOT = Path(__file__).resolve().parents[2]
HELPER = ROOT / "tests" / "helpers" / "zenoh_peer_helper.py"
CODEC = WireCodec(6, 2, 6)
DEADLINE_S = 10.0




def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


# -- config and keys ---------------------------------------------------------------------------


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


def test_keys_are_namespaced_and_validated() -> None:
    keys = Keys("run-1_a")
    assert keys.consensus(3) == "vigil/run-1_a/agent/3/consensus"
    assert keys.beacon(0) == "vigil/run-1_a/agent/0/beacon"
    assert keys.telemetry(5) == "vigil/run-1_a/agent/5/telemetry"
    assert keys.camera(2) == "vigil/run-1_a/world/camera/2"
    assert keys.truth == "vigil/run-1_a/world/truth"
    assert keys.clock == "vigil/run-1_a/world/clock"
    assert keys.all_telemetry == "vigil/run-1_a/agent/*/telemetry"
    assert keys.all_beacons == "vigil/run-1_a/agent/*/beacon"
    assert keys.source_id(keys.beacon(4)) == 4 and keys.source_id(keys.camera(1)) == 1
    assert keys.source_id(keys.truth) is None
    assert keys.source_id(Keys("other").beacon(4)) is None
    for bad in ["", "a/b", "a*", "x" * 65, "é", "a b", None]:
        with pytest.raises(ValueError, match="run_id"):
            Keys(bad)  # type: ignore[arg-type]
    for bad_id in [-1, 1.0, True, "1"]:
        with pytest.raises(ValueError, match="drone id"):
            keys.beacon(bad_id)  # type: ignore[arg-type]
    # Zenoh's own matching: a run's wildcards never reach another run, even a prefix of it.
    mine, prefix_of_mine = zenoh.KeyExpr(Keys("run").everything), Keys("run2")
    assert not mine.intersects(zenoh.KeyExpr(prefix_of_mine.beacon(1)))
    assert zenoh.KeyExpr(keys.all_beacons).intersects(zenoh.KeyExpr(keys.beacon(3)))
    assert not zenoh.KeyExpr(keys.all_beacons).intersects(zenoh.KeyExpr(keys.telemetry(3)))


# -- stores --------------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_latest_values_keep_only_the_latest() -> None:
    clock = FakeClock()
    latest: LatestValues[str] = LatestValues(clock=clock)
    assert latest.get(1) is None
    for k in range(1000):
        latest.put(1, f"v{k}", seq=k)
    assert len(latest) == 1 and latest.get(1) == ("v999", 0.0)
    assert not latest.put(1, "late", seq=998)  # an out-of-order delivery never wins
    assert latest.put(1, "no-seq")  # without seq: newest arrival wins
    clock.now += 0.25
    latest.put(2, "b")
    assert latest.get(1) == ("no-seq", 0.25)
    assert latest.fresh(0.1) == {2: "b"}
    assert latest.fresh(1.0) == {1: "no-seq", 2: "b"}
    assert latest.ages() == {1: 0.25, 2: 0.0}
    small: LatestValues[int] = LatestValues(max_sources=2)
    assert small.put(0, 0) and small.put(1, 1) and not small.put(2, 2) and small.put(1, 5)


_ITEMS = st.lists(st.tuples(st.integers(0, 4), st.integers(0, 99),
                            st.none() | st.integers(0, 5),
                            st.none() | st.floats(90.0, 110.0)), max_size=20)


@given(_ITEMS, st.integers(1, 5))
def test_latest_values_put_many_stores_what_puts_one_by_one_would(items, max_sources) -> None:
    """One ``put_many`` (a relay's beacons under one lock) leaves the store as the same
    ``put`` calls one by one would, and counts what they would have returned True for."""
    one_by_one: LatestValues[int] = LatestValues(clock=FakeClock(), max_sources=max_sources)
    batched: LatestValues[int] = LatestValues(clock=FakeClock(), max_sources=max_sources)
    stored = sum(one_by_one.put(source, value, seq=seq, arrived_s=arrived_s)
                 for source, value, seq, arrived_s in items)
    assert batched.put_many(items) == stored
    assert batched.fresh_with_ages(1e9) == one_by_one.fresh_with_ages(1e9)


@given(st.lists(st.tuples(st.integers(0, 12), st.integers(0, 1), st.integers(0, 4),
                          st.integers(0, 99)), max_size=30))
def test_mailbox_put_many_stores_what_puts_one_by_one_would(items) -> None:
    one_by_one: StepMailbox[int] = StepMailbox(max_entries=12)
    batched: StepMailbox[int] = StepMailbox(max_entries=12)
    for box in (one_by_one, batched):
        box.wait_for(4, 0, set(), 0.0)  # step 4 is current: steps 2..8 are in the window
    stored = sum(one_by_one.put(*item) for item in items)
    assert batched.put_many(items) == stored
    assert (batched.refused, batched.duplicates) == (one_by_one.refused, one_by_one.duplicates)
    for step in range(13):
        for rnd in (0, 1):
            assert batched.get(step, rnd) == one_by_one.get(step, rnd)


def test_a_mailbox_waiter_wakes_when_a_batch_completes_its_set() -> None:
    box: StepMailbox[str] = StepMailbox()
    threading.Timer(0.05, lambda: box.put_many(
        [(3, 0, j, f"b{j}") for j in range(1, 6)])).start()
    started = time.monotonic()
    assert box.wait_for(3, 0, {1, 2, 3, 4, 5}, timeout_s=5.0) == {
        j: f"b{j}" for j in range(1, 6)}
    assert time.monotonic() - started < 2.0


def test_latest_values_wait_for_wakes_on_put() -> None:
    latest: LatestValues[int] = LatestValues()
    assert not latest.wait_for({1, 2}, timeout_s=0.05)
    threading.Timer(0.05, lambda: (latest.put(1, 10, seq=3), latest.put(2, 20, seq=3))).start()
    started = time.monotonic()
    assert latest.wait_for({1, 2}, timeout_s=5.0, min_seq=3)
    assert time.monotonic() - started < 2.0
    assert not latest.wait_for({1}, timeout_s=0.01, min_seq=4)


def test_mailbox_returns_exactly_the_requested_senders() -> None:
    box: StepMailbox[str] = StepMailbox()
    for sender in range(6):
        assert box.put(4, 0, sender, f"s{sender}")
    box.put(4, 1, 2, "other round")
    box.put(5, 0, 2, "other step")
    assert box.wait_for(4, 0, {1, 3}, timeout_s=1.0) == {1: "s1", 3: "s3"}
    assert box.wait_for(4, 0, set(), timeout_s=1.0) == {}
    assert not box.put(4, 0, 1, "duplicate") and box.duplicates == 1
    assert box.get(4, 0)[1] == "s1"  # the first value is kept


def test_mailbox_times_out_with_what_it_has() -> None:
    box: StepMailbox[int] = StepMailbox()
    box.put(7, 2, 1, 11)
    started = time.monotonic()
    assert box.wait_for(7, 2, {1, 2}, timeout_s=0.2) == {1: 11}
    elapsed = time.monotonic() - started
    assert 0.19 <= elapsed < 1.0
    started = time.monotonic()
    assert box.wait_for(7, 2, {2}, timeout_s=0.0) == {}
    assert time.monotonic() - started < 0.05


def test_mailbox_wakes_as_soon_as_the_last_sender_arrives() -> None:
    box: StepMailbox[int] = StepMailbox()
    box.put(3, 0, 0, 0)
    results: dict[str, object] = {}

    def waiter() -> None:
        started = time.monotonic()
        results["got"] = box.wait_for(3, 0, {0, 1, 2}, timeout_s=10.0)
        results["elapsed"] = time.monotonic() - started

    thread = threading.Thread(target=waiter)
    thread.start()
    box.put(3, 0, 1, 1)
    box.put(3, 0, 2, 2)
    thread.join(timeout=10.0)
    assert results["got"] == {0: 0, 1: 1, 2: 2}
    assert results["elapsed"] < 5.0


def test_a_closed_mailbox_stops_waiting_now_and_later() -> None:
    box: StepMailbox[int] = StepMailbox()
    box.put(5, 0, 1, 10)
    results: dict[str, object] = {}

    def waiter() -> None:
        started = time.monotonic()
        results["got"] = box.wait_for(5, 0, {1, 2}, timeout_s=30.0)
        results["elapsed"] = time.monotonic() - started

    thread = threading.Thread(target=waiter)
    thread.start()
    box.put(5, 0, 3, 30)  # not what the waiter needs: it keeps waiting
    box.close()
    thread.join(timeout=10.0)
    assert results["got"] == {1: 10} and results["elapsed"] < 5.0
    started = time.monotonic()
    assert box.wait_for(6, 0, {1}, timeout_s=30.0) == {}
    assert time.monotonic() - started < 1.0


def test_mailbox_memory_stays_bounded() -> None:
    box: StepMailbox[int] = StepMailbox(horizon_steps=2, max_ahead_steps=3, max_entries=1000)
    for step in range(200):
        for sender in range(6):
            for rnd in range(3):
                box.put(step, rnd, sender, step)
        box.wait_for(step, 0, {0}, timeout_s=0.0)
        assert len(box) <= (2 + 1 + 3) * 6 * 3
    assert not box.put(150, 0, 0, 0)  # far behind the window
    assert not box.put(10_000, 0, 0, 0)  # far ahead of it
    assert box.refused == 2
    assert box.put(202, 0, 0, 0)  # a neighbour a step or two ahead is fine
    flood: StepMailbox[int] = StepMailbox(max_entries=10)
    assert sum(flood.put(0, r, 0, 0) for r in range(100)) == 10 and len(flood) == 10


def test_rejection_counter_is_thread_safe() -> None:
    counter = RejectionCounter()
    threads = [threading.Thread(target=lambda: [counter.reject("beacon", "bad\nline")
                                                for _ in range(1000)]) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    counter.unexpected("beacon", "KeyError: x")
    counter.reject("beacon", "time_s is not finite (nan)", "finite")
    snap = counter.snapshot()
    assert snap == {"beacon": {"rejected": 4001, "unexpected": 1,
                               "last_reason": "time_s is not finite (nan)",
                               "rules": {"source": 4000, "unexpected": 1, "finite": 1}}}
    assert counter.lines() == ["beacon: 4001 rejected, 1 unexpected (finite 1, source 4000, "
                               "unexpected 1; last: time_s is not finite (nan))"]
    assert counter.total() == 4002 and counter.wait_for_total(4002, timeout_s=0.0)
    assert not counter.wait_for_total(4003, timeout_s=0.01)
    snap["beacon"]["rules"]["finite"] = 7  # a copy
    assert counter.snapshot()["beacon"]["rules"]["finite"] == 1


# -- sockets of a process ------------------------------------------------------------------------


def _hex_ip(text: str) -> str:
    raw = bytes.fromhex(text)
    if len(raw) == 4:
        return str(ipaddress.IPv4Address(raw[::-1]))
    words = [raw[i:i + 4][::-1] for i in range(0, 16, 4)]  # four little-endian 32-bit words
    return str(ipaddress.IPv6Address(b"".join(words)))


def inet_sockets(pid: int) -> list[tuple[str, str, int]]:
    """(protocol, local address, local port) of every TCP/UDP socket the process holds."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    found = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/{pid}/net/{proto}") as table:
            next(table)
            for row in table:
                fields = row.split()
                if fields[9] in inodes:
                    address, port = fields[1].split(":")
                    found.append((proto, _hex_ip(address), int(port, 16)))
    return found


def assert_loopback_only(pid: int) -> None:
    sockets = inet_sockets(pid)
    assert sockets, "expected the process to hold zenoh sockets"
    for proto, address, _ in sockets:
        ip = ipaddress.ip_address(address)
        mapped = getattr(ip, "ipv4_mapped", None)
        assert ip.is_loopback or (mapped is not None and mapped.is_loopback), (proto, address)
        assert proto.startswith("tcp"), f"unexpected {proto} socket on {address}"


# -- child processes -----------------------------------------------------------------------------


class Child:
    """A zenoh_peer_helper process: commands in on stdin, JSON events out on stdout."""

    def __init__(self, *args: str) -> None:
        # A file, not a pipe: a chatty child never blocks. Closed in stop().
        self.stderr = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, str(HELPER), *args], cwd=ROOT, stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self.stderr, text=True, start_new_session=True)
        self.events: queue.Queue[dict] = queue.Queue()
        self.seen: list[dict] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.ready = self.expect(lambda e: e["event"] == "ready", "ready")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with contextlib.suppress(json.JSONDecodeError):
                self.events.put(json.loads(line))
        self.events.put({"event": "eof"})

    def send(self, **cmd) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()

    def next_event(self, predicate: Callable[[dict], bool], timeout_s: float) -> dict | None:
        """The first event (seen before or arriving within ``timeout_s``) matching it."""
        for event in self.seen:
            if predicate(event):
                return event
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                event = self.events.get(timeout=remaining)
            except queue.Empty:
                break
            if event["event"] == "eof":
                self.events.put(event)
                raise AssertionError(f"child exited with {self.proc.wait()}: "
                                     f"{self.stderr_tail()}")
            self.seen.append(event)
            if predicate(event):
                return event
        return None

    def stderr_tail(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-2000:]

    def expect(self, predicate: Callable[[dict], bool], what: str,
               timeout_s: float = DEADLINE_S) -> dict:
        event = self.next_event(predicate, timeout_s)
        assert event is not None, f"no {what} from child within {timeout_s} s"
        return event

    def stats(self) -> dict:
        self.seen = [e for e in self.seen if e["event"] != "stats"]
        self.send(cmd="stats")
        return self.expect(lambda e: e["event"] == "stats", "stats")

    def stop(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.send(cmd="quit")
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=3.0)
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=5.0)
        for stream in (self.proc.stdin, self.proc.stdout, self.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.close()


@pytest.fixture
def spawn() -> Iterator[Callable[..., Child]]:
    children: list[Child] = []

    def start(*args: str) -> Child:
        children.append(Child(*args))
        return children[-1]

    try:
        yield start
    finally:
        for child in children:
            child.stop()
        for child in children:  # the whole process group is gone, not just the child
            with pytest.raises(ProcessLookupError):
                os.killpg(child.proc.pid, 0)


def repeat_until(action: Callable[[], None], done: Callable[[float], object],
                 deadline_s: float = DEADLINE_S, every_s: float = 0.05):
    """Do ``action`` until ``done(wait_s)`` (which waits up to wait_s) returns something truthy.

    Zenoh propagates subscriber declarations asynchronously, so the first put after a session
    opens can legitimately find no route yet; repeating with a deadline is the bounded wait.
    """
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        action()
        result = done(every_s)
        if result:
            return result
    raise AssertionError(f"not done within {deadline_s} s")


@contextlib.contextmanager
def session(config: zenoh.Config) -> Iterator[zenoh.Session]:
    s = open_session(config)
    try:
        yield s
    finally:
        s.close()


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


def test_direct_remote_only_subscription_skips_its_own_session(spawn) -> None:
    """``direct=True`` callbacks run on zenoh's thread; ``remote_only=True`` leaves out what
    the subscribing session itself publishes on the same key expression."""
    port = free_tcp_port()
    router = spawn("--mode", "router", "--listen", endpoint(port), "--run-id", "delta")
    keys = Keys("delta")
    received: LatestValues = LatestValues()
    threads: set[str] = set()

    def handler(_key: str, beacon) -> None:
        threads.add(type(threading.current_thread()).__name__)
        received.put(beacon.sender, beacon, seq=beacon.step)

    with session(zenoh_config(mode="client", connect=[endpoint(port)])) as local:
        subscribe(local, keys.all_beacons, CODEC.decode_beacon, handler, RejectionCounter(),
                  "beacon", direct=True, remote_only=True)
        own = declare_publisher(local, keys.beacon(1))
        repeat_until(lambda: (own.put(CODEC.encode(BeaconWire.build(1, 0, 0.0, [0, 0, 1.0]))),
                              router.send(cmd="beacon", sender=4, step=0)),
                     lambda wait_s: received.wait_for({4}, wait_s))
        own.put(CODEC.encode(BeaconWire.build(1, 1, 0.02, [0, 0, 1.0])))
        router.send(cmd="beacon", sender=4, step=1)
        assert received.wait_for({4}, DEADLINE_S, min_seq=1)
    assert received.get(1) is None  # our own beacons never came back
    assert threads == {"_DummyThread"}  # zenoh's own thread, not a Python-made one


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


def iter_queue(events: queue.Queue, wait_s: float) -> list:
    """What arrives on ``events`` within ``wait_s`` (at least one get, then no waiting)."""
    try:
        out = [events.get(timeout=wait_s)]
    except queue.Empty:
        return []
    while not events.empty():
        out.append(events.get_nowait())
    return out


def test_handler_and_decoder_exceptions_never_reach_zenoh(spawn) -> None:
    port = free_tcp_port()
    peer = spawn("--mode", "peer", "--listen", endpoint(port), "--run-id", "gamma")
    keys = Keys("gamma")
    rejections = RejectionCounter()
    received: LatestValues = LatestValues()

    def handler(key: str, beacon) -> None:
        if beacon.step == 1:
            raise RuntimeError("handler bug")
        received.put(beacon.sender, beacon, seq=beacon.step)

    def decoder(payload: bytes):
        if payload == b"boom":
            raise KeyError("decoder bug")
        return CODEC.decode_beacon(payload)

    with session(zenoh_config(mode="peer", connect=[endpoint(port)])) as local:
        subscribe(local, keys.all_beacons, decoder, handler, rejections, "beacon")
        repeat_until(lambda: peer.send(cmd="beacon", sender=4, step=0),
                     lambda wait_s: received.wait_for({4}, wait_s))
        peer.send(cmd="raw", key=keys.beacon(4), hex=b"boom".hex())
        peer.send(cmd="beacon", sender=4, step=1)
        peer.send(cmd="beacon", sender=4, step=2)
        assert received.wait_for({4}, DEADLINE_S, min_seq=2)
        snap = rejections.snapshot()["beacon"]
        assert snap["unexpected"] == 2 and snap["rejected"] == 0
        assert "handler raised RuntimeError: handler bug" in snap["last_reason"]
        assert received.get(4)[0].step == 2


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


def test_run_ids_isolate_swarms_sharing_one_router(spawn) -> None:
    """Even on one shared router, a run's subscribers only ever receive their own run."""
    port = free_tcp_port()
    alpha = spawn("--mode", "router", "--listen", endpoint(port), "--run-id", "alpha")
    beta = spawn("--mode", "client", "--connect", endpoint(port), "--run-id", "beta")
    alpha2 = spawn("--mode", "client", "--connect", endpoint(port), "--run-id", "alpha")

    def seen_by(child: Child, drone: int, step: int) -> Callable[[float], object]:
        return lambda wait_s: child.next_event(
            lambda e: e["event"] == "value" and e["sender"] == drone and e["step"] == step,
            wait_s)

    # beta publishes the same drone ids and steps as alpha, on its own keys.
    repeat_until(lambda: beta.send(cmd="beacon", sender=1, step=0), seen_by(beta, 1, 0))
    repeat_until(lambda: alpha2.send(cmd="beacon", sender=1, step=0), seen_by(alpha, 1, 0))
    repeat_until(lambda: (beta.send(cmd="beacon", sender=2, step=1),
                          alpha.send(cmd="beacon", sender=2, step=1)), seen_by(alpha2, 2, 1))
    # alpha's raw vigil/** subscriber proves beta's traffic really reaches the shared router...
    repeat_until(lambda: beta.send(cmd="beacon", sender=3, step=2),
                 lambda wait_s: "beta" in alpha.stats()["runs_seen"])
    # ...while its typed subscribers (vigil/alpha/agent/*/beacon) never delivered any of it.
    for child, run in ((alpha, "alpha"), (alpha2, "alpha"), (beta, "beta")):
        values = [e for e in child.seen if e["event"] == "value"]
        assert values and all(e["key"].startswith(f"vigil/{run}/") for e in values), values
        assert child.stats()["rejections"] == {}


def test_link_faults_are_checked_and_off_by_default() -> None:
    assert not LinkFaults().active
    assert LinkFaults(drop_rate=0.1).active and LinkFaults(delay_steps=2).active
    for bad in ({"drop_rate": 1.0}, {"drop_rate": -0.1}, {"drop_rate": float("nan")},
                {"delay_steps": -1}):
        with pytest.raises(ValueError):
            LinkFaults(**bad)


def faulty_link(faults: LinkFaults, steps: int, step_period_s: float = 0.0
                ) -> tuple[FaultyPublisher, dict[int, float], dict[int, float], dict[int, float]]:
    """Beacons of steps 1..``steps`` through a ``FaultyPublisher`` between two peer sessions,
    one put per step after ``advance(step)``. Returns the publisher and, by step, when each
    message was put, when its step's advance released what was due, and the sent time the
    receiver read from its Zenoh timestamp (only for the messages that arrived)."""
    port = free_tcp_port()
    keys = Keys("faults")
    arrived: dict[int, float] = {}
    got = threading.Event()

    def on_sent(beacon: BeaconWire, unix_s: float) -> None:
        arrived[beacon.step] = unix_s
        got.set()

    with session(zenoh_config(mode="peer", listen=[endpoint(port)])) as hub, \
            session(zenoh_config(mode="peer", connect=[endpoint(port)])) as client:
        subscribe(hub, keys.all_beacons, CODEC.decode_beacon, lambda _k, _b: None,
                  RejectionCounter(), "beacon", on_sent_time=on_sent)
        publisher = declare_publisher(client, keys.beacon(2))
        repeat_until(lambda: put_stamped(client, publisher, CODEC.encode(
            BeaconWire.build(2, 0, 0.0, [0, 0, 1.0]))), got.wait)
        faulty = FaultyPublisher(client, publisher, faults)
        put_s: dict[int, float] = {}
        released_s: dict[int, float] = {}
        for step in range(1, steps + 1):
            released_s[step] = time.time()
            faulty.advance(step)
            put_s[step] = time.time()
            faulty.put(CODEC.encode(BeaconWire.build(2, step, 0.0, [0, 0, 1.0])))
            if step_period_s:
                time.sleep(step_period_s)  # the step period of a realtime loop
        # A last, unfaulted message on the same publisher: once it is in, so is every
        # earlier one (one publisher, one link: in order).
        put_stamped(client, publisher, CODEC.encode(BeaconWire.build(2, steps + 1, 0.0,
                                                                     [0, 0, 1.0])))
        deadline = time.monotonic() + DEADLINE_S
        while steps + 1 not in arrived and time.monotonic() < deadline:
            got.clear()
            got.wait(0.05)
    assert steps + 1 in arrived
    arrived.pop(0, None)
    arrived.pop(steps + 1, None)
    return faulty, put_s, released_s, arrived


def test_a_lossy_link_loses_that_share_of_messages_and_delivers_the_rest() -> None:
    faulty, _put, _released, arrived = faulty_link(LinkFaults(drop_rate=0.3, seed=5), 2000)
    assert faulty.offered == 2000 and faulty.dropped + faulty.sent == 2000
    assert len(arrived) == faulty.sent  # what was not lost arrived
    assert 0.3 - 0.04 < faulty.dropped / 2000 < 0.3 + 0.04  # 4 standard deviations


def test_a_slow_link_sends_each_message_k_steps_late_stamped_when_it_was_put() -> None:
    faulty, put_s, released_s, arrived = faulty_link(LinkFaults(delay_steps=2), 30,
                                                     step_period_s=0.01)
    assert faulty.delayed == 30 and faulty.sent == 28  # the last two are still held
    assert sorted(arrived) == list(range(1, 29))
    for step, sent_s in arrived.items():
        # Stamped at its put (the age a receiver computes includes the delay) and released
        # by the advance two steps later, not before.
        assert abs(sent_s - put_s[step]) < 0.005
        assert released_s[step + 2] - put_s[step] >= 0.015


@contextlib.contextmanager
def beacons_to_a_hub(run_id: str) -> Iterator[tuple[zenoh.Session, Keys, LatestValues,
                                                   Callable[[int], None], Callable[[], None]]]:
    """A hub session; ``seen``, a plain subscriber of it keeping the newest beacon step
    heard (what has arrived, beside the subscription under test); ``put(step)``, drone 2's
    beacon of that step from a client session; ``settle()``, until every beacon put so far
    has been handed to every subscription of the hub.

    ``seen`` hearing a beacon does not mean the subscription under test has it yet: the hub
    hands each sample to its subscriptions one after the other, and on a loaded machine the
    test's thread ran between the two (a CI run drained an empty ring). ``settle`` puts a
    fence on another key over the same link and waits until the hub has heard it: the hub
    handles a link's messages in order, so every beacon before it has been handed out."""
    port = free_tcp_port()
    keys = Keys(run_id)
    seen = LatestValues()
    fenced = LatestValues()
    fence_key = f"{KEY_ROOT}/{run_id}/test/fence"
    with session(zenoh_config(mode="peer", listen=[endpoint(port)])) as hub, \
            session(zenoh_config(mode="peer", connect=[endpoint(port)])) as client:
        subscribe(hub, keys.all_beacons, CODEC.decode_beacon,
                  lambda _k, b: seen.put(0, b.step, seq=b.step), RejectionCounter(), "beacon")
        subscribe(hub, fence_key, int, lambda _k, n: fenced.put(0, n, seq=n),
                  RejectionCounter(), "fence")
        publisher = declare_publisher(client, keys.beacon(2))
        fence = declare_publisher(client, fence_key)
        fences = itertools.count(1)

        def put(step: int) -> None:
            publisher.put(CODEC.encode(BeaconWire.build(2, step, 0.0, [0, 0, 1.0])))

        def settle() -> None:
            n = next(fences)
            repeat_until(lambda: fence.put(str(n).encode()),
                         lambda wait_s: fenced.wait_for([0], wait_s, min_seq=n))

        yield hub, keys, seen, put, settle


def test_a_ring_subscription_waits_for_its_drain_and_keeps_only_the_newest() -> None:
    """``keep_latest=K``: samples wait in zenoh until ``drain()``, which runs the callback on
    the caller's thread (no thread of its own); a burst of 200 between two drains leaves the
    newest K, in order."""
    taken: list[tuple[int, int]] = []  # (step, thread id)

    def on_value(_key: str, beacon, arrived_s: float) -> None:
        taken.append((beacon.step, threading.get_ident()))

    with beacons_to_a_hub("ring") as (hub, keys, seen, put, settle):
        threads_before = threading.active_count()
        ring = subscribe(hub, keys.all_beacons, CODEC.decode_beacon, on_value,
                         RejectionCounter(), "beacon", keep_latest=4)
        assert threading.active_count() == threads_before  # no thread of ours
        repeat_until(lambda: put(0), lambda wait_s: seen.wait_for([0], wait_s))
        settle()
        assert ring.drain() >= 1 and taken and taken[-1][0] == 0
        taken.clear()
        assert ring.drain() == 0 and not taken  # nothing new
        for step in range(1, 201):
            put(step)
        assert seen.wait_for([0], DEADLINE_S, min_seq=200)  # the burst has come
        settle()
        assert ring.drain() == 4
        assert [step for step, _ in taken] == [197, 198, 199, 200]
        assert {thread for _, thread in taken} == {threading.get_ident()}
        ring.undeclare()
        ring.undeclare()  # twice is harmless
        assert ring.drain() == 0
    with pytest.raises(ValueError, match="keep_latest"):
        subscribe(hub, "x", CODEC.decode_beacon, on_value, RejectionCounter(), "beacon",
                  keep_latest=0)


def test_a_backlog_subscription_loses_nothing_and_makes_zenoh_wait_when_full() -> None:
    """``backlog=K``: samples wait in a FIFO inside zenoh until ``drain()`` (the caller's
    thread, at most K a drain); when it is full, the receiving session waits (a plain
    subscriber beside it hears no more) instead of dropping: a burst of 200 comes out whole
    and in order."""
    backlog = 4
    taken: list[tuple[int, int]] = []  # (step, thread id)

    def on_value(_key: str, beacon) -> None:
        taken.append((beacon.step, threading.get_ident()))

    with beacons_to_a_hub("fifo") as (hub, keys, seen, put, settle):
        fifo = subscribe(hub, keys.all_beacons, CODEC.decode_beacon, on_value,
                         RejectionCounter(), "beacon", backlog=backlog)
        repeat_until(lambda: put(0), lambda wait_s: seen.wait_for([0], wait_s))
        settle()
        while fifo.drain():
            pass
        taken.clear()
        for step in range(1, 201):
            put(step)
        assert seen.wait_for([0], DEADLINE_S, min_seq=backlog)  # the FIFO has filled
        time.sleep(0.3)  # nobody drains: the session's receiving waits for room
        stalled_at = seen.get(0)[0]
        assert stalled_at < 200, "a full FIFO let its session receive on"
        assert fifo.drain() == backlog  # one queue's worth at most per drain
        deadline = time.monotonic() + DEADLINE_S
        while len(taken) < 200 and time.monotonic() < deadline:
            fifo.drain()
        assert [step for step, _ in taken] == list(range(1, 201))
        assert {thread for _, thread in taken} == {threading.get_ident()}
        assert seen.wait_for([0], DEADLINE_S, min_seq=200)  # and the session received on
        fifo.undeclare()
        assert fifo.drain() == 0
    for wrong in ({"backlog": 0}, {"backlog": True}, {"backlog": 4, "direct": True},
                  {"backlog": 4, "keep_latest": 4}):
        with pytest.raises(ValueError, match=r"backlog|keep_latest"):
            subscribe(hub, "x", CODEC.decode_beacon, on_value, RejectionCounter(), "beacon",
                      **wrong)


def test_a_blocking_receive_takes_samples_in_order_and_ends_at_a_close_or_a_deadline(
) -> None:
    """``receive_one`` runs the callback on the waiting thread for each sample in turn;
    ``BlockingReceives`` ends a wait on a silent FIFO when closed (at once) or once its
    armed deadline has passed (within a check period), and says which; disarmed, it lets a
    wait go on."""
    taken: list[tuple[int, int]] = []  # (step, thread id)

    def on_value(_key: str, beacon) -> None:
        taken.append((beacon.step, threading.get_ident()))

    def waited_s(fifo: DrainedSubscriber, since_s: float) -> tuple[bool, float]:
        """``receive_one``'s outcome and the time from ``since_s`` (taken before the timer or
        the deadline was set: a wait measured from after it could end a little under it)."""
        got = fifo.receive_one()
        return got, time.monotonic() - since_s

    with beacons_to_a_hub("blocking") as (hub, keys, seen, put, settle):
        fifos = [subscribe(hub, keys.all_beacons, CODEC.decode_beacon, on_value,
                           RejectionCounter(), "beacon", backlog=64) for _ in range(2)]
        repeat_until(lambda: put(0), lambda wait_s: seen.wait_for([0], wait_s))
        settle()
        for fifo in fifos:
            while fifo.drain():
                pass
        taken.clear()
        for step in (1, 2, 3):
            put(step)
        for fifo in fifos:
            assert all(fifo.receive_one() for _ in range(3))
        assert [step for step, _ in taken] == [1, 2, 3] * 2
        assert {thread for _, thread in taken} == {threading.get_ident()}

        closing = BlockingReceives(fifos[:1], check_period_s=0.05)
        closing.arm(time.monotonic() + 60.0)
        since_s = time.monotonic()
        threading.Timer(0.2, closing.close).start()
        got, after_s = waited_s(fifos[0], since_s)
        assert not got and 0.2 <= after_s < 5.0 and not closing.expired
        assert not fifos[0].receive_one()  # gone for good

        expiring = BlockingReceives(fifos[1:], check_period_s=0.05)
        expiring.arm(None)
        threading.Timer(0.3, lambda: put(4)).start()
        assert fifos[1].receive_one() and taken[-1][0] == 4  # disarmed: it waited
        assert not expiring.expired
        since_s = time.monotonic()
        expiring.arm(since_s + 0.2)
        got, after_s = waited_s(fifos[1], since_s)
        assert not got and 0.2 <= after_s < 5.0 and expiring.expired
        for watch in (closing, expiring):
            watch.join(5.0)
    with pytest.raises(ValueError, match="check_period_s"):
        BlockingReceives([], check_period_s=0.0)


@pytest.mark.wallclock
def test_a_ring_dates_a_stamped_sample_from_its_put_not_from_its_drain() -> None:
    """A sample taken from its ring 0.2 s after it came is dated from its Zenoh timestamp
    (the sender's put), bounded by the previous drain; an unstamped one from the drain."""
    port = free_tcp_port()
    keys = Keys("ringage")
    arrivals: dict[int, float] = {}
    seen = LatestValues()

    def on_value(_key: str, beacon, arrived_s: float) -> None:
        arrivals[beacon.step] = arrived_s

    with session(zenoh_config(mode="peer", listen=[endpoint(port)])) as hub, \
            session(zenoh_config(mode="peer", connect=[endpoint(port)])) as client:
        ring = subscribe(hub, keys.all_beacons, CODEC.decode_beacon, on_value,
                         RejectionCounter(), "beacon", keep_latest=8)
        subscribe(hub, keys.all_beacons, CODEC.decode_beacon,
                  lambda _k, b: seen.put(b.step, b), RejectionCounter(), "beacon")
        publisher = declare_publisher(client, keys.beacon(2))

        def put(step: int, stamped: bool) -> None:
            payload = CODEC.encode(BeaconWire.build(2, step, 0.0, [0, 0, 1.0]))
            if stamped:
                put_stamped(client, publisher, payload)
            else:
                publisher.put(payload)

        repeat_until(lambda: put(0, True), lambda wait_s: seen.wait_for([0], wait_s))
        ring.drain()
        before_s = time.monotonic()
        put(1, True)
        put(2, False)
        assert seen.wait_for([1, 2], DEADLINE_S)
        time.sleep(0.2)  # the owner is busy: the samples wait in the ring
        drained_s = time.monotonic()
        ring.drain()
        assert before_s <= arrivals[1] <= before_s + 0.05, arrivals[1] - before_s
        assert drained_s <= arrivals[2] <= time.monotonic()


def test_a_preemption_between_the_drains_clock_reads_dates_a_sample_late_never_early(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The drain dates a stamped sample from two clocks read one after the other; here every
    read takes 1 ms (a preemption between them, as a loaded CI machine had it): the sample,
    put at monotonic 100.5 s, is dated at or after its put and no later than the drain, never
    before the put (read in the other order it came out 1 ms early)."""
    offset_s = 1.7e9  # wall clock − monotonic clock
    clock = [101.0]

    def tick() -> float:
        clock[0] += 0.001
        return clock[0]

    class Stamp:
        def get_time_as_ntp64(self) -> Stamp:
            return self

        def as_secs_f64(self) -> float:
            return 100.5 + offset_s

    class Sample:
        timestamp = Stamp()

    class Handler:
        def __init__(self) -> None:
            self.samples = [Sample()]

        def try_recv(self) -> Sample | None:
            return self.samples.pop() if self.samples else None

    class Subscriber:
        def __init__(self) -> None:
            self.handler = Handler()

    arrivals: list[float] = []
    ring = DrainedSubscriber(Subscriber(), lambda _sample, arrived_s: arrivals.append(arrived_s))
    ring._last_drain_s = 100.0  # the previous drain began before the put
    monkeypatch.setattr(time, "monotonic", tick)
    monkeypatch.setattr(time, "time", lambda: tick() + offset_s)
    assert ring.drain() == 1
    monkeypatch.undo()
    assert 100.5 <= arrivals[0] <= 100.5 + 0.002, arrivals


def test_a_process_left_with_ring_subscriptions_exits_cleanly() -> None:
    """No ``undeclare``, no session close, samples left in the rings: the process still
    exits cleanly (a thread woken inside zenoh while Python finalizes used to abort it)."""
    script = (
        "import time\n"
        "from swarm.net.transport import subscribe, zenoh_config, open_session, RejectionCounter\n"
        "s = open_session(zenoh_config(mode='peer'))\n"
        "subs = [subscribe(s, f'r/{i}', bytes, lambda k, v: None, RejectionCounter(), 'x',\n"
        "                  keep_latest=4) for i in range(4)]\n"
        "s.put('r/0', b'x'); time.sleep(0.2)\n"
    )
    for _ in range(3):
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              timeout=60, cwd=Path(__file__).resolve().parents[2])
        assert done.returncode == 0, done.stderr[-2000:]
        assert "FATAL" not in done.stderr


# A router and a client in one fresh process exchange messages; then the zenoh threads alive
# are listed by name (their pools: app, tx, rx, acc, net), numbers dropped.
THREADS_SCRIPT = """
import json, os, sys, time
from swarm.net.transport import (RejectionCounter, declare_publisher, open_session, subscribe,
                                 zenoh_config)
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
    """open_session's default thread pools (transport.ZENOH_RUNTIME_DEFAULT): receiving,
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
