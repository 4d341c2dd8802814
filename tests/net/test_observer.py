"""The observers' one way in (``swarm.net.observer``): joining the world's router while it
starts, and the subscriptions the launcher, the dashboard and a remote recorder hold."""

from __future__ import annotations

import queue
import threading
import time

import pytest
from msgspec import structs

from swarm.net.keys import Keys
from swarm.net.observer import (
    FEED_BACKLOG,
    ObserverFeed,
    drain_in_turn,
    join_router,
    subscribe_observer,
)
from swarm.net.session import TransportError, declare_publisher, open_session, zenoh_config
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import RejectionCounter, subscribe
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.wire_samples import CODEC, MESSAGES, PAYLOADS

DEADLINE_S = 10.0


def test_join_router_retries_until_the_router_is_up() -> None:
    """The world may still be starting: tries fail until its router listens, then the
    observer is in."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tries: list[float] = []
    routers = []

    def count_and_start_the_router_on_the_third() -> None:
        tries.append(time.monotonic())
        if len(tries) == 3:
            routers.append(open_session(zenoh_config(mode="router", listen=[endpoint])))

    try:
        client = join_router([endpoint], DEADLINE_S,
                             before_each_try=count_and_start_the_router_on_the_third)
        client.close()
    finally:
        for router in routers:
            router.close()
    assert len(tries) == 3
    assert tries[2] - tries[0] >= 0.2  # paused 0.1 s between tries


def test_join_router_gives_up_at_its_deadline_or_when_told() -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"  # nobody listens
    started = time.monotonic()
    with pytest.raises(TransportError):
        join_router([endpoint], 0.3)
    assert 0.3 <= time.monotonic() - started < 5.0

    class ChildDied(Exception):
        pass

    def died() -> None:
        raise ChildDied

    with pytest.raises(ChildDied):
        join_router([endpoint], DEADLINE_S, before_each_try=died)


def test_an_observer_hears_what_it_asked_for_and_counts_what_it_rejects() -> None:
    """Telemetry and clock always; truth, beacons and camera frames only with a callback;
    each payload decoded by the run's codec, junk counted under its kind."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("observertest")
    heard: queue.Queue[tuple[str, object]] = queue.Queue()

    def into(kind: str):
        return lambda _key, message: heard.put((kind, message))

    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    try:
        observer = join_router([endpoint], DEADLINE_S)
        full = RejectionCounter()
        lean = RejectionCounter()
        held = [subscribe_observer(observer, keys, CODEC, full, on_telemetry=into("telemetry"),
                                   on_clock=into("clock"), on_truth=into("truth"),
                                   on_beacon=into("beacon"), on_camera=into("camera")),
                subscribe_observer(observer, keys, CODEC, lean, on_telemetry=into("lean"),
                                   on_clock=into("lean"))]
        assert [len(subs) for subs in held] == [5, 2]
        telemetry = MESSAGES["telemetry"]
        sent = {"telemetry": (keys.telemetry(telemetry.drone), PAYLOADS["telemetry"]),
                "clock": (keys.clock, PAYLOADS["clock"]),
                "truth": (keys.truth, PAYLOADS["truth"]),
                "beacon": (keys.beacon(MESSAGES["beacon"].sender), PAYLOADS["beacon"]),
                "camera": (keys.camera(MESSAGES["camera"].drone), PAYLOADS["camera"])}
        got: dict[str, list[object]] = {}
        deadline = time.monotonic() + DEADLINE_S
        # Subscriptions propagate asynchronously: publish again until each kind arrived.
        while set(got) != {*sent, "lean"} and time.monotonic() < deadline:
            for key, payload in sent.values():
                router.put(key, payload)
            try:
                while True:
                    kind, message = heard.get(timeout=0.05)
                    got.setdefault(kind, []).append(message)
            except queue.Empty:
                pass
        assert set(got) == {*sent, "lean"}
        for kind in sent:
            assert got[kind][0] == MESSAGES[kind]
        assert {type(m).__name__ for m in got["lean"]} == {"TelemetryWire", "ClockWire"}

        router.put(keys.truth, b"\x93junk")
        router.put(keys.clock, b"\x93junk")
        assert full.wait_for_total(2, DEADLINE_S) and lean.wait_for_total(1, DEADLINE_S)
        assert full.snapshot()["truth"]["rejected"] == 1
        assert full.snapshot()["truth"]["last_reason"].endswith(f" on {keys.truth}")
        assert full.snapshot()["clock"]["rejected"] == 1
        assert "truth" not in lean.snapshot() and lean.snapshot()["clock"]["rejected"] == 1
        for subs in held:
            for sub in subs:
                sub.undeclare()
        observer.close()
    finally:
        router.close()


def test_the_feed_hands_over_in_batches_on_its_thread_and_loses_nothing_at_close() -> None:
    """``ObserverFeed``: the callbacks run on the feed's one thread, every ``period_s``, not
    on one thread per subscription; a feed that has not drained yet (a period longer than
    the test) hands everything that came to its callbacks when it closes, in order."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("feedtest")
    telemetry = MESSAGES["telemetry"]
    key = keys.telemetry(telemetry.drone)
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    try:
        observer = join_router([endpoint], DEADLINE_S)
        seen = LatestValues()  # a plain subscriber of the observer: what has arrived
        witness = subscribe(observer, keys.all_telemetry, CODEC.decode_telemetry,
                            lambda _k, tel: seen.put(0, tel.step, seq=tel.step),
                            RejectionCounter(), "telemetry")
        fast: list[tuple[int, str]] = []
        slow: list[tuple[int, str]] = []

        def into(out: list[tuple[int, str]]):
            return lambda _key, tel: out.append((tel.step, threading.current_thread().name))

        feeds = [ObserverFeed(subscribe_observer(observer, keys, CODEC, RejectionCounter(),
                                                 on_telemetry=into(out),
                                                 on_clock=lambda _k, _c: None,
                                                 backlog=FEED_BACKLOG), period_s=period_s)
                 for out, period_s in ((fast, 0.02), (slow, 600.0))]
        deadline = time.monotonic() + DEADLINE_S
        while not seen.wait_for([0], 0.05) and time.monotonic() < deadline:
            router.put(key, CODEC.encode(structs.replace(telemetry, step=0)))  # until subscribed
        publisher = declare_publisher(router, key)  # waits for room: zenoh drops none
        for step in range(1, 101):
            publisher.put(CODEC.encode(structs.replace(telemetry, step=step)))
        assert seen.wait_for([0], DEADLINE_S, min_seq=100)
        while not (fast and fast[-1][0] == 100) and time.monotonic() < deadline:
            time.sleep(0.01)  # the feed's own thread hands them over
        assert [step for step, _ in fast if step > 0] == list(range(1, 101))
        assert {name for _, name in fast} == {"observer-feed"}
        assert slow == []  # its first drain is ten minutes away
        feeds[1].close()
        assert [step for step, _ in slow if step > 0] == list(range(1, 101))
        assert {name for _, name in slow} == {threading.current_thread().name}
        feeds[1].close()  # twice is harmless
        feeds[0].close()
        assert not any(t.name == "observer-feed" for t in threading.enumerate())
        witness.undeclare()
        observer.close()
    finally:
        router.close()



def test_a_feed_far_behind_loses_nothing_and_holds_up_nobody() -> None:
    """A launcher on an overloaded machine fell 12 s behind: 20 000 telemetry samples wait
    for a feed that has not drained (far more than the 8192 a first version held, whose full
    FIFO stopped the session's receiving until zenoh closed the link); the router's puts are
    never held up, and close() hands over every sample, in order."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("feedbehind")
    telemetry = MESSAGES["telemetry"]
    key = keys.telemetry(telemetry.drone)
    count = 20_000
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    observer = join_router([endpoint], DEADLINE_S)
    seen = LatestValues()
    witness = subscribe(observer, keys.all_telemetry, CODEC.decode_telemetry,
                        lambda _k, tel: seen.put(0, tel.step, seq=tel.step),
                        RejectionCounter(), "telemetry")
    got: list[int] = []
    feed = ObserverFeed(subscribe_observer(
        observer, keys, CODEC, RejectionCounter(),
        on_telemetry=lambda _k, tel: got.append(tel.step), on_clock=lambda _k, _c: None,
        backlog=FEED_BACKLOG), period_s=600.0)
    try:
        deadline = time.monotonic() + DEADLINE_S
        while not seen.wait_for([0], 0.05) and time.monotonic() < deadline:
            router.put(key, CODEC.encode(structs.replace(telemetry, step=0)))
        payloads = [CODEC.encode(structs.replace(telemetry, step=step))
                    for step in range(1, count + 1)]
        # A blocking publisher, as in lockstep: a full queue waits instead of dropping (a
        # session.put drops: 86 of 20 000 were lost so beside a busy test, before any feed saw
        # them). Were the feed to hold samples up, these puts would wait until the deadline.
        blocking = declare_publisher(router, key)
        publisher = threading.Thread(target=lambda: [blocking.put(p) for p in payloads],
                                     daemon=True)
        publisher.start()
        publisher.join(3 * DEADLINE_S)
        assert not publisher.is_alive(), "the router's puts were held up by the feed"
        assert seen.wait_for([0], 3 * DEADLINE_S, min_seq=count)  # the session received on
        assert got == []
        feed.close()
        assert [step for step in got if step > 0] == list(range(1, count + 1))
        witness.undeclare()
    finally:  # after a failure too: drained, a full FIFO lets zenoh's receiving go on
        feed.close()
        observer.close()
        router.close()

class Waiting:
    """Stands for a drained subscription with ``count`` samples waiting; logs each take."""

    def __init__(self, name: str, count: int, log: list[tuple[str, int]]) -> None:
        self.name, self.count, self.log = name, count, log

    def drain(self, max_samples: int | None = None) -> int:
        taken = self.count if max_samples is None else min(self.count, max_samples)
        self.count -= taken
        self.log.append((self.name, taken))
        return taken


def test_a_drain_takes_the_kinds_in_turn_so_a_flood_of_one_holds_up_none_other() -> None:
    """A launcher that fell behind has thousands of telemetry samples waiting: the truth
    and the clock are taken after the first 256 of them, not after all."""
    log: list[tuple[str, int]] = []
    kinds = [Waiting("telemetry", 1000, log), Waiting("truth", 3, log),
             Waiting("clock", 0, log), Waiting("camera", 300, log)]
    assert drain_in_turn(kinds, 256) == 1303
    assert [k.count for k in kinds] == [0, 0, 0, 0]
    assert log[:4] == [("telemetry", 256), ("truth", 3), ("clock", 0), ("camera", 256)]
    assert [taken for name, taken in log if name == "telemetry"] == [256, 256, 256, 232]
    log.clear()
    assert drain_in_turn(kinds, 256) == 0 and len(log) == 4  # one round when nothing waits
    flood = [Waiting("telemetry", 10_000, log)]
    assert drain_in_turn(flood, 256, stop=lambda: True) == 256  # told to stop: one round


@pytest.mark.parametrize(("options", "message"), [
    ({"period_s": 0.0}, "period_s must be > 0"),
    ({"pass_samples": 0}, "pass_samples must be an integer >= 1"),
    ({"pass_samples": True}, "pass_samples must be an integer >= 1"),
])
def test_a_feed_refuses_a_period_or_pass_size_it_could_not_run_with(
        options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ObserverFeed([], **options)


def test_telemetry_batches_reach_the_observer_one_step_at_a_time() -> None:
    """A lockstep agent sends its telemetry several steps per message
    (``TelemetryBatchWire``): the observer's ``on_telemetry`` gets each step's message, in
    order, as for messages sent one by one; a batch it refuses is counted, whole."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("batchtest")
    telemetry = MESSAGES["telemetry"]
    key = keys.telemetry(telemetry.drone)

    def steps(*ks: int) -> list[bytes]:
        return [CODEC.encode(structs.replace(telemetry, step=k)) for k in ks]

    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    try:
        observer = join_router([endpoint], DEADLINE_S)
        got: list[int] = []
        rejections = RejectionCounter()
        subs = subscribe_observer(
            observer, keys, CODEC, rejections, on_telemetry=lambda _k, tel: got.append(tel.step),
            on_clock=lambda _k, _c: None, backlog=FEED_BACKLOG)
        deadline = time.monotonic() + DEADLINE_S
        while not got and time.monotonic() < deadline:  # until the subscription is up
            router.put(key, steps(0)[0])
            time.sleep(0.01)
            drain_in_turn(subs, 256)
        publisher = declare_publisher(router, key)
        publisher.put(CODEC.encode_telemetry_batch(steps(1, 2, 3)))
        publisher.put(steps(4)[0])
        publisher.put(CODEC.encode_telemetry_batch(steps(5, 6)))
        publisher.put(CODEC.encode_telemetry_batch(steps(7, 8)).replace(
            steps(8)[0], steps(7)[0]))  # 7 then 7: refused whole
        publisher.put(CODEC.encode_telemetry_batch(steps(9, 10)))
        while not (got and got[-1] == 10) and time.monotonic() < deadline:
            time.sleep(0.01)
            drain_in_turn(subs, 256)
        assert [k for k in got if k > 0] == [1, 2, 3, 4, 5, 6, 9, 10]
        assert rejections.snapshot()["telemetry"]["rejected"] == 1
        assert "item 1 has step 7, not after 7" in rejections.snapshot()["telemetry"][
            "last_reason"]
        for sub in subs:
            sub.undeclare()
        observer.close()
    finally:
        router.close()
