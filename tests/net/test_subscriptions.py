"""Subscriptions (swarm.net.subscriptions): validated deliveries, rejection counts, rings, FIFOs
and blocking receives, over real sessions on loopback.

No sleeps hide races: cross-process checks wait for the child's report with a deadline, and a
publish is repeated until it is seen (route establishment is asynchronous in Zenoh).
"""

from __future__ import annotations

import contextlib
import itertools
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from swarm.messages.wire import BeaconWire
from swarm.net.keys import KEY_ROOT, Keys
from swarm.net.session import declare_publisher, put_stamped, zenoh_config
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import BlockingReceives, DrainedSubscriber, RejectionCounter, subscribe
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.zenoh_tools import CODEC, DEADLINE_S, endpoint, repeat_until, session


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


@contextlib.contextmanager
def beacons_to_a_hub(run_id: str) -> Iterator[tuple[zenoh.Session, Keys, LatestValues,
                                                   Callable[[int], None], Callable[[], None]]]:
    """A hub session; ``seen``, a plain subscriber of it keeping the newest beacon step
    heard (what has arrived, beside the subscription under test); ``put(step)``, drone 2's
    beacon of that step from a client session; ``settle()``, until every beacon put so far
    has been handed to every subscription of the hub.

    ``seen`` hearing a beacon does not mean the subscription under test has it yet: the hub
    hands each sample to its subscriptions one after the other, and on a loaded machine the
    test's thread can run between the two (its drain then finds nothing). ``settle`` puts a
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
    exits cleanly (a thread woken inside zenoh while Python finalizes must not abort it)."""
    script = (
        "import time\n"
        "from swarm.net.session import open_session, zenoh_config\n"
        "from swarm.net.subscriptions import RejectionCounter, subscribe\n"
        "s = open_session(zenoh_config(mode='peer'))\n"
        "subs = [subscribe(s, f'r/{i}', bytes, lambda k, v: None, RejectionCounter(), 'x',\n"
        "                  keep_latest=4) for i in range(4)]\n"
        # The scenario: the process leaves while the sample is in a ring (nothing to poll
        # without draining it, which the scenario rules out).
        "s.put('r/0', b'x'); time.sleep(0.2)\n"
    )
    for _ in range(3):
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              timeout=60, cwd=Path(__file__).resolve().parents[2])
        assert done.returncode == 0, done.stderr[-2000:]
        assert "FATAL" not in done.stderr
