"""The stores of deliveries (swarm.net.stores): LatestValues and StepMailbox."""

from __future__ import annotations

import threading
import time

from hypothesis import given
from hypothesis import strategies as st

from swarm.net.stores import LatestValues, StepMailbox


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
