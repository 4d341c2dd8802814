"""Zenoh subscriptions whose payloads are validated before anyone sees them, and the counts
of what was dropped.

``subscribe`` declares a subscriber that decodes each payload with a ``WireCodec`` decoder; a
``WireError`` (or anything unexpected) is counted in a ``RejectionCounter`` and the payload
dropped — no exception ever reaches zenoh's thread.

zenoh-python 1.x runs Python callbacks on a dedicated Python thread per subscriber by default
(``handlers.Callback(indirect=True)``), in arrival order per subscriber; ``subscribe(...,
direct=True)`` runs them on zenoh's receiving thread instead (one thread hop and one
wake-up fewer per message: what a lockstep step waits on). The queue in front of that
Python thread has no bound: a consumer that falls behind (an overloaded machine) grows it
without end and works through ever older data. Two bounded forms instead keep the samples
inside zenoh until their owner takes them (``DrainedSubscriber.drain``, on the owner's thread,
in batches): ``subscribe(..., keep_latest=K)`` for consumers that only want the newest data
(realtime agents), a ring of K samples whose oldest is dropped when it is full; and
``subscribe(..., backlog=K)`` for consumers that must see everything (the launcher's
recorder), a FIFO of K samples on which zenoh's receiving waits when it is full (so sized
never to fill). The stores of ``swarm.net.stores`` are what make those deliveries safe to
read from the agent's own thread.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import zenoh

from swarm.messages.rules import WireError
from swarm.net.session import MAX_REASON_CHARS

T = TypeVar("T")


class RejectionCounter:
    """Thread-safe counts of dropped payloads per key kind, by the rule each broke, with the
    last reason of each kind.

    ``rejected``: the payload was not a valid wire message (``WireError``: its ``rule``, e.g.
    "finite", "range", "shape") or came from a source it may not come from ("source").
    ``unexpected``: the decoder or the value handler raised anything else — a bug, counted
    instead of crashing.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._counts: dict[str, dict[str, Any]] = {}
        self._total = 0

    def _add(self, kind: str, field: str, reason: str, rule: str) -> None:
        reason = " ".join(str(reason).split())[:MAX_REASON_CHARS]
        with self._cond:
            entry = self._counts.setdefault(
                kind, {"rejected": 0, "unexpected": 0, "last_reason": "", "rules": {}})
            entry[field] += 1
            entry["rules"][rule] = entry["rules"].get(rule, 0) + 1
            entry["last_reason"] = reason
            self._total += 1
            self._cond.notify_all()

    def reject(self, kind: str, reason: str, rule: str = "source") -> None:
        self._add(kind, "rejected", reason, rule)

    def unexpected(self, kind: str, reason: str) -> None:
        self._add(kind, "unexpected", reason, "unexpected")

    def total(self) -> int:
        """All payloads dropped so far, every kind and both causes."""
        with self._cond:
            return self._total

    def lines(self) -> list[str]:
        """One line per kind that dropped anything, with its last reason (for a log)."""
        lines = []
        for kind, entry in sorted(self.snapshot().items()):
            rules = ", ".join(f"{rule} {count}" for rule, count in sorted(entry["rules"].items()))
            lines.append(f"{kind}: {entry['rejected']} rejected, {entry['unexpected']} "
                         f"unexpected ({rules}; last: {entry['last_reason']})")
        return lines

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """``{kind: {"rejected": n, "unexpected": m, "last_reason": str, "rules": {rule: n}}}``
        (a copy)."""
        with self._cond:
            return {kind: {**entry, "rules": dict(entry["rules"])}
                    for kind, entry in self._counts.items()}

    def wait_for_total(self, count: int, timeout_s: float) -> bool:
        """Block until at least ``count`` payloads were dropped in all; False at the deadline."""
        with self._cond:
            return self._cond.wait_for(lambda: self._total >= count, timeout=timeout_s)


def subscribe(
    session: zenoh.Session,
    key: str,
    decode: Callable[[bytes], T],
    on_value: Callable[..., None],  # (key, value), or (key, value, arrived_s): see below
    rejections: RejectionCounter,
    kind: str,
    *,
    max_payload_bytes: int = 1 << 20,
    direct: bool = False,
    remote_only: bool = False,
    on_sent_time: Callable[[T, float], None] | None = None,
    keep_latest: int | None = None,
    backlog: int | None = None,
) -> zenoh.Subscriber | DrainedSubscriber:
    """Declare a callback subscriber on ``key`` (wildcards allowed).

    Each sample's payload goes through ``decode`` (e.g. ``codec.decode_beacon``); a valid value
    is passed to ``on_value(key_of_the_sample, value)``. A ``WireError`` is counted as rejected
    under ``kind``; any other exception from the decoder or from ``on_value`` is counted as
    unexpected with its type and message. Nothing propagates into zenoh's thread. The
    subscriber lives until ``undeclare()`` or the session closes; ``on_value`` runs on zenoh's
    callback thread, so it should only store the value (e.g. in a ``StepMailbox``).

    ``direct``: run the callback on zenoh's receiving thread (no hop through a Python thread
    of its own); it then holds up that link's reception while it runs (and while it waits for
    the GIL), so keep it short, and never use it in a process that hosts a router.
    ``remote_only``: leave out what this session publishes itself (e.g. an agent's own beacon
    on ``agent/*/beacon``).
    ``on_sent_time(value, unix_s)``: called before ``on_value`` for a sample that carries a
    Zenoh timestamp (``put_stamped``), with its time — the sender's clock at the put, so the
    receiver sees the age of the data including the hop (exact on one host; across hosts as
    good as the clocks' synchronisation).
    ``keep_latest``: instead of zenoh's callback thread and its unbounded queue, a ring of
    this many samples that waits in zenoh (no Python, no GIL) until its owner calls
    ``DrainedSubscriber.drain()``, which runs the callback on the owner's thread for every
    sample waiting; when more arrive between two drains, the oldest are dropped. Memory and
    the age of what is handled stay bounded on an overloaded machine, and receiving never
    preempts the owner's computation. Only for consumers that want the newest value per
    source (size the ring to hold at least one drain interval's worth of sources).
    ``on_value`` is then called as ``on_value(key, value, arrived_s)`` with the sample's
    estimated arrival on ``time.monotonic`` (``DrainedSubscriber.drain``).
    ``backlog``: the same, but a FIFO of this many samples from which nothing is dropped:
    when it is full, zenoh's receiving thread waits until ``drain()`` makes room, and with
    it every delivery of that session. That is no back pressure across a router: its sends
    to a session that stopped receiving block, and zenoh closes the link after ~5 s. Size it
    never to fill (``swarm.net.observer.FEED_BACKLOG``: nothing is allocated up front). For
    consumers that must see every sample but can take them in batches (the launcher's
    collector and recorder: one wake-up per drain instead of one per sample), or that wait
    for them one at a time on their own thread (``DrainedSubscriber.receive_one``: a lockstep
    agent's neighbours' consensus). ``on_value(key, value)`` as without it.
    """

    # Every reason names the key the payload came on (which drone, which stream): what an
    # operator needs to find the sender.
    def callback(sample: zenoh.Sample, arrived_s: float | None = None) -> None:
        try:
            payload = sample.payload
            if len(payload) > max_payload_bytes:
                rejections.reject(kind, f"payload of {len(payload)} bytes exceeds the "
                                        f"{max_payload_bytes}-byte limit on {sample.key_expr}",
                                  "size")
                return
            value = decode(payload.to_bytes())
        except WireError as exc:
            rejections.reject(kind, f"{exc.reason} on {sample.key_expr}", exc.rule)
            return
        except BaseException as exc:  # never into zenoh's thread
            rejections.unexpected(kind, f"decoder raised {type(exc).__name__}: {exc} on "
                                        f"{sample.key_expr}")
            return
        try:
            if on_sent_time is not None and (stamp := sample.timestamp) is not None:
                on_sent_time(value, stamp.get_time_as_ntp64().as_secs_f64())
            if arrived_s is None:
                on_value(str(sample.key_expr), value)
            else:
                on_value(str(sample.key_expr), value, arrived_s)
        except BaseException as exc:
            rejections.unexpected(kind, f"handler raised {type(exc).__name__}: {exc} on "
                                        f"{sample.key_expr}")

    origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
    if keep_latest is None and backlog is None:
        handler = zenoh.handlers.Callback(callback, indirect=not direct)
        return session.declare_subscriber(key, handler, allowed_origin=origin)
    for name, size in (("keep_latest", keep_latest), ("backlog", backlog)):
        if size is not None and (direct or isinstance(size, bool)
                                 or not (isinstance(size, int) and size >= 1)):
            raise ValueError(f"{name} must be an integer >= 1 and excludes direct, got "
                             f"{size!r}")
    if keep_latest is not None and backlog is not None:
        raise ValueError("keep_latest (a ring) and backlog (a FIFO) exclude each other")
    if backlog is not None:
        return DrainedSubscriber(session.declare_subscriber(
            key, zenoh.handlers.FifoChannel(backlog), allowed_origin=origin), callback,
            arrival_times=False, max_per_drain=backlog)
    assert keep_latest is not None  # both None returned the callback subscriber above
    return DrainedSubscriber(session.declare_subscriber(
        key, zenoh.handlers.RingChannel(keep_latest), allowed_origin=origin), callback)


class DrainedSubscriber:
    """A subscriber whose samples wait inside zenoh until ``drain()``: in a ring, the oldest
    dropped when it is full (``subscribe(..., keep_latest=K)``), or in a FIFO on which
    zenoh's receiving waits when it is full (``subscribe(..., backlog=K)``).

    Why the owner drains: a Python thread running the callback as samples come costs every
    sample a thread wake-up and two GIL hand-overs, and preempts the owner's step when one
    comes during it (on Case 2 scaled to N = 12 in realtime, 44 % of the steps were late with
    such a thread, 7 % with the ring).

    ``arrival_times``: pass each sample's estimated arrival to the callback (rings: the
    realtime agent dates what it takes); without, the callback gets the sample alone.
    ``max_per_drain``: a drain takes at most this many samples (a FIFO: one queue's worth),
    so that it returns even while samples come faster than it takes them.
    """

    def __init__(self, subscriber: zenoh.Subscriber,
                 callback: Callable[..., None], *, arrival_times: bool = True,
                 max_per_drain: int | None = None) -> None:
        self._subscriber = subscriber
        self._queue = subscriber.handler
        self._callback = callback
        self._arrival_times = arrival_times
        self._max_per_drain = math.inf if max_per_drain is None else max_per_drain
        self._declared = True
        self._last_drain_s = -math.inf

    def drain(self, max_samples: int | None = None) -> int:
        """Run the callback on every sample waiting (up to ``max_per_drain``, and up to
        ``max_samples`` if given), in arrival order, on this thread; the number taken.

        With ``arrival_times``, each sample's arrival (``time.monotonic``) is estimated from
        its Zenoh timestamp (``put_stamped``: the sender's clock at the put) and bounded to
        the interval it can have arrived in, after the previous drain began and before this
        one: on one host never before the put and late by at most the time between this
        drain's two clock reads (the wall clock is read first, so that a preemption between
        them makes the estimate late, not early), and off by at most that interval across
        hosts whatever their clocks say. A sample without a timestamp counts as arrived now."""
        if not self._declared:
            return 0
        now_unix = time.time()
        now_s = time.monotonic()
        since_s, self._last_drain_s = self._last_drain_s, now_s
        taken = 0
        limit = self._max_per_drain if max_samples is None else min(max_samples,
                                                                     self._max_per_drain)
        while taken < limit:
            try:
                sample = self._queue.try_recv()
            except zenoh.ZError:  # the session closed: nothing more will come
                return taken
            if sample is None:
                return taken
            taken += 1
            if not self._arrival_times:
                self._callback(sample)
                continue
            arrived_s = now_s
            stamp = sample.timestamp
            if stamp is not None:
                sent_ago_s = now_unix - stamp.get_time_as_ntp64().as_secs_f64()
                arrived_s = min(now_s, max(since_s, now_s - sent_ago_s))
            self._callback(sample, arrived_s)
        return taken

    def receive_one(self) -> bool:
        """Wait for the next sample and run the callback on it, on this thread (a FIFO:
        ``subscribe(..., backlog=K)``, whose samples come in order); False, at once, when the
        subscription is undeclared (another thread's way to end the wait,
        ``BlockingReceives``) or its session closed. The wait holds no GIL; zenoh wakes this
        thread alone when the sample arrives, where a callback subscription takes the GIL on
        zenoh's receiving thread and then wakes the waiter."""
        try:
            sample = self._queue.recv()
        except zenoh.ZError:  # undeclared, or the session closed: nothing more will come
            return False
        if self._arrival_times:
            self._callback(sample, time.monotonic())
        else:
            self._callback(sample)
        return True

    def undeclare(self) -> None:
        if not self._declared:
            return
        self._declared = False
        with contextlib.suppress(zenoh.ZError):  # the session is closed already
            self._subscriber.undeclare()


class BlockingReceives:
    """A way out of ``DrainedSubscriber.receive_one`` waits: zenoh's ``recv`` takes no
    timeout, so a thread of this class undeclares ``subscribers`` (every wait in progress on
    them returns False at once) when ``close()`` is called, or once a deadline set with
    ``arm`` has passed. It looks at the deadline every ``check_period_s``: arming costs the
    waiter an assignment, not a wake-up of this thread. Once it has fired, the subscriptions
    are gone for good: for waits whose failure ends their owner (a lockstep agent whose
    neighbour fell silent, or whose mission ended). ``expired`` says which it was."""

    def __init__(self, subscribers: Iterable[DrainedSubscriber], *,
                 check_period_s: float = 0.25,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not check_period_s > 0:
            raise ValueError(f"BlockingReceives: check_period_s must be > 0, got "
                             f"{check_period_s!r}")
        self._subscribers = list(subscribers)
        self._check_period_s = check_period_s
        self._clock = clock
        self._deadline_s: float | None = None
        self._closed = threading.Event()
        self.expired = False
        self._thread = threading.Thread(target=self._watch, name="receive-deadline",
                                        daemon=True)
        self._thread.start()

    def arm(self, deadline_s: float | None) -> None:
        """End the waits if they go on past ``deadline_s`` (on ``clock``); None: no deadline."""
        self._deadline_s = deadline_s

    def close(self) -> None:
        """End every wait now (safe from any thread, also zenoh's, and more than once)."""
        self._closed.set()

    def join(self, timeout_s: float | None = None) -> None:
        self._thread.join(timeout_s)

    def _watch(self) -> None:
        while not self._closed.wait(self._check_period_s):
            deadline_s = self._deadline_s
            if deadline_s is not None and self._clock() > deadline_s:
                self.expired = True
                break
        for sub in self._subscribers:
            sub.undeclare()
