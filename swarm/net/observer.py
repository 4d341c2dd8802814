"""An observer's view of a run, in one place: a client session on the world's router and
the subscriptions an observer holds (the launcher, the dashboard, a remote recorder).

``join_router(endpoints, timeout_s, ...)`` (``swarm.net.session``) retries while the world
starts up;
``subscribe_observer(session, keys, codec, rejections, ...)`` subscribes to telemetry and the
clock, and to the truth, the beacons, the camera frames and images for whoever passes a
callback;
``ObserverFeed`` takes the same subscriptions made as FIFOs inside zenoh and hands their
samples to the callbacks in batches, on one thread of its own (the launcher: nothing may be lost,
and a wake-up per message was most of what it cost).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from swarm.messages.wire import (
    BeaconWire,
    CameraFrameWire,
    CameraImageWire,
    ClockWire,
    TelemetryWire,
    TruthWire,
    WireCodec,
)
from swarm.net.keys import Keys
from swarm.net.session import join_router
from swarm.net.subscriptions import DrainedSubscriber, RejectionCounter, subscribe

__all__ = ["FEED_BACKLOG", "ObserverFeed", "drain_in_turn", "join_router",
           "subscribe_observer"]

OnMessage = Callable[[str, Any], None]


def subscribe_observer(session: zenoh.Session, keys: Keys, codec: WireCodec,
                       rejections: RejectionCounter, *,
                       on_telemetry: Callable[[str, TelemetryWire], None],
                       on_clock: Callable[[str, ClockWire], None],
                       on_truth: Callable[[str, TruthWire], None] | None = None,
                       on_beacon: Callable[[str, BeaconWire], None] | None = None,
                       on_camera: Callable[[str, CameraFrameWire], None] | None = None,
                       on_image: Callable[[str, CameraImageWire], None] | None = None,
                       backlog: int | None = None) -> list[Any]:
    """Subscribe to every drone's telemetry and the world's clock, and to the truth, the
    beacons, the camera frames and the rendered cameras' images where a callback is given;
    each payload decoded by ``codec``, each rejection counted in ``rejections`` under its
    kind. Keep the returned subscribers: a subscription lives as long as its handle.
    ``backlog``: FIFOs of that many samples, handed to the callbacks by ``drain()``
    (``subscribe``), instead of a Python thread of zenoh's per subscription. A telemetry
    sample may carry several steps (``TelemetryBatchWire``): ``on_telemetry`` gets each
    step's message, in order."""

    def on_telemetry_items(key: str, items: tuple[TelemetryWire, ...]) -> None:
        for tel in items:
            on_telemetry(key, tel)

    wanted: list[tuple[str, Callable[[bytes], Any], OnMessage | None, str]] = [
        (keys.all_telemetry, codec.decode_telemetry_items, on_telemetry_items, "telemetry"),
        (keys.truth, codec.decode_truth, on_truth, "truth"),
        (keys.clock, codec.decode_clock, on_clock, "clock"),
        (keys.all_beacons, codec.decode_beacon, on_beacon, "beacon"),
        (keys.all_cameras, codec.decode_camera, on_camera, "camera"),
        (keys.all_images, codec.decode_image, on_image, "image"),
    ]
    return [subscribe(session, key, decode, callback, rejections, kind, backlog=backlog)
            for key, decode, callback, kind in wanted if callback is not None]


# How often the feed hands what came to its callbacks; how many samples of a kind it takes
# before it turns to the next kind (so that the truth and the clock are never stuck behind
# thousands of telemetry messages when the launcher is behind); and how many samples of a
# kind may wait. That bound is not meant to be reached: a full FIFO stops the whole session's
# receiving, and zenoh closes a link whose blocking messages wait for more than 5 s
# (measured: Case 2 at N = 24 in realtime with a recording, on two cores, filled a FIFO of
# 8192 camera frames in 12 s and the launcher lost the rest of the run). Memory is only taken
# while samples wait (a FIFO allocates nothing up front), as zenoh's own callback queue did.
FEED_PERIOD_S = 0.02
FEED_PASS_SAMPLES = 256
FEED_BACKLOG = 1 << 20


class ObserverFeed:
    """``subscribe_observer(..., backlog=FEED_BACKLOG)``'s subscriptions (FIFOs inside
    zenoh), drained every ``period_s`` by one thread of the feed, which runs the callbacks a
    batch at a time.

    Zenoh's default runs a subscription's callbacks on a Python thread of its own, woken at
    every sample: with a recording at N = 12 in realtime that was 36 wake-ups of the launcher
    per 20 ms step. Here a sample waits in zenoh (no Python, no GIL) until the next drain;
    what the callbacks see is up to ``period_s`` later, in arrival order within each kind.
    A drain takes the kinds in turn, ``pass_samples`` of each at a time, until none has more
    waiting (``drain_in_turn``). ``close()`` stops the thread, hands over what is still
    waiting and undeclares: nothing received before it is lost.
    """

    def __init__(self, subscribers: Sequence[DrainedSubscriber], *,
                 period_s: float = FEED_PERIOD_S,
                 pass_samples: int = FEED_PASS_SAMPLES) -> None:
        if not period_s > 0:
            raise ValueError(f"ObserverFeed: period_s must be > 0, got {period_s!r}")
        if isinstance(pass_samples, bool) or not (isinstance(pass_samples, int)
                                                  and pass_samples >= 1):
            # drain_in_turn stops after a round that took fewer: with 0 it never would
            raise ValueError(f"ObserverFeed: pass_samples must be an integer >= 1, got "
                             f"{pass_samples!r}")
        if not all(isinstance(sub, DrainedSubscriber) for sub in subscribers):
            raise ValueError("ObserverFeed drains subscriptions made with "
                             "subscribe_observer(..., backlog=FEED_BACKLOG)")
        self.period_s = period_s
        self.pass_samples = pass_samples
        self._subscribers = list(subscribers)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="observer-feed", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            drain_in_turn(self._subscribers, self.pass_samples, self._stop.is_set)

    def close(self) -> None:
        """Stop draining, hand over what is still waiting, then undeclare; safe to call more
        than once."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
        subscribers, self._subscribers = self._subscribers, []
        for sub in subscribers:
            sub.drain()
            sub.undeclare()


def drain_in_turn(subscribers: Sequence[DrainedSubscriber], pass_samples: int,
                  stop: Callable[[], bool] = lambda: False) -> int:
    """Drain ``subscribers`` in turn, at most ``pass_samples`` from each at a time, until a
    round takes fewer than that from every one of them (or ``stop()``); how many in all."""
    total = 0
    while True:
        taken = [sub.drain(pass_samples) for sub in subscribers]
        total += sum(taken)
        if max(taken, default=0) < pass_samples or stop():
            return total
