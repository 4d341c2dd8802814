"""Fault injection (swarm.net.faults): a lossy or slow link between two real sessions."""

from __future__ import annotations

import threading
import time

import pytest

from swarm.messages.wire import BeaconWire
from swarm.net.faults import FaultyPublisher, LinkFaults
from swarm.net.keys import Keys
from swarm.net.session import declare_publisher, put_stamped, zenoh_config
from swarm.net.subscriptions import RejectionCounter, subscribe
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.zenoh_tools import CODEC, DEADLINE_S, endpoint, repeat_until, session


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
