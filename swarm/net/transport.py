"""A thin Zenoh layer (SPEC §12): loopback-only session configs, key names, and thread-safe
stores that turn callback deliveries into what an agent step needs.

- ``zenoh_config`` builds a session config with explicit endpoints only: no multicast scouting
  and no default listener (zenoh's own default listens on ``tcp/[::]:<port>`` on every
  interface and scouts on UDP multicast 224.0.0.224:7446). A swarm started with loopback
  endpoints therefore creates no traffic outside 127.0.0.0/8. With a ``TlsIdentity``
  (``swarm.net.security``, the config's ``[security]``) every link is mutual TLS (``tls/...``
  endpoints only), and a router can be given an ``access_control`` block to enforce.
- ``Keys`` names every key expression under ``vigil/<run_id>/``; different run ids never match.
- ``subscribe`` declares a callback subscriber that decodes each payload with a ``WireCodec``
  decoder; a ``WireError`` (or anything unexpected) is counted in a ``RejectionCounter`` and the
  payload dropped — no exception ever reaches zenoh's thread.
- ``LatestValues`` (realtime mode): the newest value per source with its age; never a queue.
- ``StepMailbox`` (lockstep mode): values keyed (step, round, sender) and a blocking
  ``wait_for`` on a condition variable, pruned so memory stays bounded.
- ``LinkFaults`` / ``FaultyPublisher`` (a test option, off by default): drop a fraction of
  one key's outgoing messages at random, or send each a number of steps late, as a lossy or
  slow radio link would.

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
never to fill). The stores here are what make those deliveries safe to read from the agent's
own thread.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import math
import os
import random
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Final, Generic, Literal, TypeVar

import zenoh

from swarm.errors import VigilError
from swarm.messages.wire import WireError
from swarm.net.security import TlsIdentity

T = TypeVar("T")

Mode = Literal["peer", "client", "router"]
MODES: Final = ("peer", "client", "router")
PROTOCOLS: Final = ("tcp", "udp", "tls")
KEY_ROOT: Final = "vigil"

_RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                       r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
_MAX_REASON_CHARS: Final = 300
TX_DATA_QUEUE_BATCHES: Final = 16  # per link and priority; zenoh allocates batches lazily
# Zenoh's thread pools (its ZENOH_RUNTIME variable; the user's own setting wins). By default
# zenoh receives on two "rx" worker threads, accepts on "acc", manages links on "net", and a
# message handed from one pool to another wakes a thread of the other: on this project's 2-core
# VM, waking a thread costs the waker ~20 µs of CPU. Here receiving, accepting and link
# management run on zenoh's one "app" thread; transmission keeps its own thread, so that a
# put that waits for room in a full queue (congestion control "block": from a main thread, or
# from a subscription's own Python thread as the world's lockstep relay) always has a thread
# left to empty it. Measured with the same code
# side by side (Case 2, lockstep, 20 s; voluntary context switches per simulated step): the
# world 74 → 41, each agent 18 → 10; Case 2 scaled to N = 12 in realtime (20 s, two
# interleaved rounds): 1.77 / 1.73 → 1.40 / 1.34 cores, late steps 11.7 / 9.5 → 0.4 / 0 %.
# The price: one receiving thread per process. A router forwarding to a link whose queue is
# full (TX_DATA_QUEUE_BATCHES of up to 64 kB) waits on that thread until the link drains;
# if the process itself is that link's reader (a router and a client of it in one process:
# tests only, never the swarm's processes) it waits for itself until zenoh gives up (~5 s).
# A callback on the receiving thread (``subscribe(direct=True)``) must only store, never put.
ZENOH_RUNTIME_VARIABLE: Final = "ZENOH_RUNTIME"
ZENOH_RUNTIME_DEFAULT: Final = "(rx: (handover: app), acc: (handover: app), net: (handover: app))"


class TransportError(VigilError, RuntimeError):
    """A Zenoh session could not be opened (one line: what and why)."""


# -- configuration -------------------------------------------------------------------------------


def parse_endpoint(endpoint: str, *, role: Literal["listen", "connect"] = "connect"
                   ) -> tuple[str, str, int]:
    """Split ``"<tcp|udp|tls>/<host>:<port>"`` into (protocol, host, port), or raise
    ``ValueError``.

    Hosts are IPv4 addresses, bracketed IPv6 addresses (``tcp/[::1]:7447``) or host names. Port
    0 (any free port) is allowed for ``listen`` only. Zenoh itself accepts malformed strings at
    configuration time and fails later, so every endpoint goes through here first.
    """
    if not isinstance(endpoint, str):
        raise ValueError(f"zenoh {role} endpoint must be a string like 'tcp/127.0.0.1:7447', "
                         f"got {type(endpoint).__name__}")
    shown = endpoint if len(endpoint) <= 80 else endpoint[:77] + "..."
    expected = "expected '<tcp|udp|tls>/<host>:<port>', e.g. 'tcp/127.0.0.1:7447'"
    proto, slash, rest = endpoint.partition("/")
    if not slash or proto not in PROTOCOLS:
        raise ValueError(f"zenoh {role} endpoint {shown!r}: {expected}")
    host, colon, port_text = rest.rpartition(":")
    if not colon or not host or not port_text.isdigit() or len(port_text) > 5:
        raise ValueError(f"zenoh {role} endpoint {shown!r}: {expected}")
    port = int(port_text)
    if not (0 if role == "listen" else 1) <= port <= 65535:
        raise ValueError(f"zenoh {role} endpoint {shown!r}: port {port} out of range "
                         f"({'0' if role == 'listen' else '1'}-65535)")
    if host.startswith("[") and host.endswith("]"):
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            raise ValueError(f"zenoh {role} endpoint {shown!r}: {host} is not an IPv6 "
                             "address") from None
    elif re.fullmatch(r"[0-9.]+", host):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise ValueError(f"zenoh {role} endpoint {shown!r}: {host} is not an IPv4 "
                             "address") from None
    elif not _HOSTNAME.match(host):
        raise ValueError(f"zenoh {role} endpoint {shown!r}: {host!r} is not a host name; "
                         f"{expected}")
    return proto, host, port


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for endpoints on 127.0.0.0/8, ``[::1]`` or ``localhost``."""
    _, host, _ = parse_endpoint(endpoint, role="listen")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def local_endpoint(port: int, *, tls: bool = False) -> str:
    """``tcp/127.0.0.1:<port>``, or ``tls/...`` when the swarm runs with ``[security]``."""
    return f"{'tls' if tls else 'tcp'}/127.0.0.1:{port}"


def check_tls_endpoints(endpoints: Iterable[str], *, tls: bool) -> None:
    """``ValueError`` unless every endpoint is ``tls/...`` with TLS on, and none is without."""
    for endpoint in endpoints:
        if endpoint.startswith("tls/") != tls:
            raise ValueError(f"zenoh endpoint {endpoint[:80]!r}: " + (
                "plain, but [security] is on: use tls/<host>:<port>" if tls
                else "tls needs certificates: set [security] tls_dir in the config"))


def zenoh_config(
    *,
    mode: Mode = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    connect_timeout_s: float | None = None,
    shared_memory: bool = False,
    tls: TlsIdentity | None = None,
    access_control: dict[str, Any] | None = None,
) -> zenoh.Config:
    """A Zenoh session config with explicit endpoints only.

    - ``mode``: "router" (routes between everything connected to it), "peer" or "client".
    - ``listen`` / ``connect``: exact endpoints such as ``"tcp/127.0.0.1:7447"``; empty ``listen``
      means the session accepts no connections at all (zenoh's default would listen on every
      interface).
    - Multicast scouting is off. Gossip scouting stays on for peers and routers: it only tells
      sessions already connected about each other's *listen* endpoints (so peers behind one
      hub can link up directly), and those are exactly the explicit ones given here.
    - ``connect_timeout_s``: keep retrying the connect endpoints this long at open, then fail
      (default: zenoh's per-mode behaviour — a client fails at once if nothing answers, a peer
      opens anyway and keeps retrying in the background).
    - ``shared_memory`` is off by default: payloads here are small, and a SIGKILLed process
      must not leave segments behind in /dev/shm.
    - ``tls``: mutual TLS with this identity (``swarm.net.security``); every endpoint must then be
      ``tls/...``, and without it none may be.
    - ``access_control``: a zenoh ``access_control`` block (``security.router_access_control``)
      that this session enforces on the messages it exchanges with the others.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
    if isinstance(listen, str) or isinstance(connect, str):
        raise ValueError("zenoh listen/connect must be sequences of endpoint strings, "
                         "not one string")
    listen, connect = list(listen), list(connect)
    for endpoint in listen:
        parse_endpoint(endpoint, role="listen")
    for endpoint in connect:
        parse_endpoint(endpoint, role="connect")
    check_tls_endpoints([*listen, *connect], tls=tls is not None)
    if connect_timeout_s is not None and not (isinstance(connect_timeout_s, int | float)
                                              and 0 < connect_timeout_s <= 3600):
        raise ValueError(f"connect_timeout_s must be in (0, 3600] s, got {connect_timeout_s!r}")
    config = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": mode,
        "listen/endpoints": listen,
        "listen/exit_on_failure": True,  # a busy port is an error at open, not a silent gap
        "connect/endpoints": connect,
        # Reconnect quickly after a hub restarts. ``connect/retry`` is null by default, so its
        # fields cannot be inserted one by one ("unknown key"): the object goes in whole.
        "connect/retry": {"period_init_ms": 100, "period_max_ms": 1000,
                          "period_increase_factor": 2},
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": mode != "client",
        "scouting/gossip/multihop": False,
        "transport/shared_memory/enabled": bool(shared_memory),
        # Room for a whole step's burst per link. An express message is a batch of its own
        # and zenoh's default data queue holds 2 batches, so a world step (N camera frames,
        # truth, clock) toward one subscriber overflowed whenever the link's tx task was not
        # scheduled within wait_before_drop (1 ms) on a loaded machine: droppable (realtime)
        # messages were lost, ~10 % of the truth toward a recording launcher.
        "transport/link/tx/queue/size/data": TX_DATA_QUEUE_BATCHES,
    }
    if tls is not None:
        settings.update(tls.zenoh_settings())
    if access_control is not None:
        settings["access_control"] = access_control
    if connect_timeout_s is not None:
        settings["connect/timeout_ms"] = max(1, round(connect_timeout_s * 1000))
        settings["connect/exit_on_failure"] = True
    for key, value in settings.items():
        config.insert_json5(key, json.dumps(value))
    return config


def open_session(config: zenoh.Config) -> zenoh.Session:
    """``zenoh.open`` with a one-line ``TransportError`` (busy port, nothing to connect to).

    Zenoh's thread pools are this process's ``ZENOH_RUNTIME`` if set, else
    ``ZENOH_RUNTIME_DEFAULT`` (read once per process, when its first session opens)."""
    os.environ.setdefault(ZENOH_RUNTIME_VARIABLE, ZENOH_RUNTIME_DEFAULT)
    try:
        return zenoh.open(config)
    except Exception as exc:  # zenoh.ZError carries a multi-line Rust trace
        message = " ".join(str(exc).split())
        message = re.sub(r" at /\S+\.rs:\d+\.?", "", message)
        raise TransportError(f"cannot open zenoh session: {message[:_MAX_REASON_CHARS]}"
                             ) from None


def put_stamped(session: zenoh.Session, publisher: zenoh.Publisher, payload: bytes) -> None:
    """``publisher.put(payload)`` with a Zenoh timestamp of now (the session's hybrid logical
    clock, which follows the wall clock): receivers learn when the data left
    (``subscribe(..., on_sent_time=...)``)."""
    publisher.put(payload, timestamp=session.new_timestamp())


def declare_publisher(session: zenoh.Session, key: str, *, block: bool = True,
                      express: bool = False) -> zenoh.Publisher:
    """A publisher for one key.

    ``block=True`` (lockstep): a full transmission queue waits instead of dropping — a lost
    consensus message would stall the neighbours until their timeout. ``block=False``
    (realtime): drop rather than delay; only the newest value matters. ``express`` puts each
    message in a batch (a write, a wake-up at the receiver) of its own. Off by default: zenoh
    batches only what queues up while a link is busy, so an idle link still sends at once,
    and a burst (the world's camera frames, a beacon and a consensus message to the same
    agent) goes out in fewer writes. Measured on a synthetic lockstep (the swarm's messages
    without its compute, 6 agents, 2 cores, medians of 3): 4.5 instead of 5.3 ms per step,
    ~20 % less router CPU.
    """
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        express=express,
    )


@dataclass(frozen=True)
class LinkFaults:
    """What a ``FaultyPublisher`` does to the messages put through it (a test option)."""

    drop_rate: float = 0.0  # each message is lost with this probability
    delay_steps: int = 0  # each message that is not lost goes out this many steps late
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.drop_rate) and 0.0 <= self.drop_rate < 1.0):
            raise ValueError(f"drop rate must be in [0, 1), got {self.drop_rate!r}")
        if self.delay_steps < 0:
            raise ValueError(f"delay must be >= 0 steps, got {self.delay_steps!r}")

    @property
    def active(self) -> bool:
        return self.drop_rate > 0.0 or self.delay_steps > 0


class FaultyPublisher:
    """Puts messages with a Zenoh timestamp of when they were *sent* (``put_stamped``), after
    losing some at random and holding the others back a number of steps: a receiver sees
    what a lossy, slow link would deliver, the age of the data included.

    ``advance(step)`` at the start of each step sends what is due: a message put during step
    k goes out at the start of step k + ``delay_steps``. Used from one thread (the step's).
    """

    def __init__(self, session: zenoh.Session, publisher: zenoh.Publisher,
                 faults: LinkFaults) -> None:
        self._session, self._publisher, self.faults = session, publisher, faults
        self._random = random.Random(faults.seed)
        self._held: deque[tuple[int, Any, bytes]] = deque()  # (due step, timestamp, payload)
        self._step = 0
        self.offered = self.sent = self.dropped = self.delayed = 0

    def advance(self, step: int) -> None:
        self._step = step
        while self._held and self._held[0][0] <= step:
            _due, stamp, payload = self._held.popleft()
            self._publisher.put(payload, timestamp=stamp)
            self.sent += 1

    def put(self, payload: bytes) -> None:
        stamp = self._session.new_timestamp()
        self.offered += 1
        if self._random.random() < self.faults.drop_rate:
            self.dropped += 1
        elif self.faults.delay_steps:
            self._held.append((self._step + self.faults.delay_steps, stamp, payload))
            self.delayed += 1
        else:
            self._publisher.put(payload, timestamp=stamp)
            self.sent += 1


# -- key expressions -----------------------------------------------------------------------------


def _index(name: str, i: Any) -> int:
    if isinstance(i, bool) or not isinstance(i, int) or i < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {i!r}")
    return i


class Keys:
    """Key expressions of one run, all under ``vigil/<run_id>/``."""

    def __init__(self, run_id: str) -> None:
        if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
            raise ValueError("run_id must be 1-64 characters of [A-Za-z0-9_-], got "
                             f"{run_id!r:.80}")
        self.run_id = run_id
        self.prefix = f"{KEY_ROOT}/{run_id}"
        self.truth = f"{self.prefix}/world/truth"
        self.clock = f"{self.prefix}/world/clock"
        # Every drone's beacon, relayed by the world (lockstep: step k's; realtime: the newest).
        self.beacon_relay = f"{self.prefix}/world/beacons"
        self.all_consensus = f"{self.prefix}/agent/*/consensus"
        self.all_beacons = f"{self.prefix}/agent/*/beacon"
        self.all_telemetry = f"{self.prefix}/agent/*/telemetry"
        self.all_cameras = f"{self.prefix}/world/camera/*"
        self.everything = f"{self.prefix}/**"
        self._source = re.compile(
            rf"^{re.escape(self.prefix)}/(?:agent/(\d{{1,9}})/(?:consensus|beacon|telemetry)"
            rf"|world/camera/(\d{{1,9}}))$")

    def consensus(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/consensus"

    def beacon(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/beacon"

    def telemetry(self, i: int) -> str:
        return f"{self.prefix}/agent/{_index('drone id', i)}/telemetry"

    def camera(self, i: int) -> str:
        return f"{self.prefix}/world/camera/{_index('drone id', i)}"

    def source_id(self, key: str) -> int | None:
        """The drone id in an agent or camera key of this run (None for other keys).

        A subscriber on a wildcard can check it against the id inside the payload.
        """
        match = self._source.match(str(key))
        if match is None:
            return None
        return int(match.group(1) or match.group(2))

    def __repr__(self) -> str:
        return f"Keys({self.run_id!r})"


# -- rejection counting --------------------------------------------------------------------------


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
        reason = " ".join(str(reason).split())[:_MAX_REASON_CHARS]
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


# -- stores --------------------------------------------------------------------------------------


class LatestValues(Generic[T]):
    """Thread-safe latest value per source, with its receipt time (realtime mode).

    A source is any hashable: a drone id, or e.g. ``(drone, round)`` for consensus rounds.

    ``put(source, value, seq=step)`` ignores a value older (lower ``seq``) than the stored one,
    so a late out-of-order delivery never replaces newer data. Memory: one entry per source,
    at most ``max_sources`` sources. Every clock reading happens under the lock, so an age
    is never negative (a reading taken before a concurrent ``put`` stored a newer time gave
    e.g. a negative neighbour age, which the telemetry encoder then refused).
    """

    def __init__(self, *, clock: Callable[[], float] = time.monotonic,
                 max_sources: int = 4096) -> None:
        self._clock = clock
        self._max_sources = max_sources
        self._cond = threading.Condition()
        self._values: dict[Hashable, tuple[T, float, int | None]] = {}

    def put(self, source: Hashable, value: T, *, seq: int | None = None,
            arrived_s: float | None = None) -> bool:
        """Store ``value`` as the newest from ``source``; False if refused (older, or full).
        ``arrived_s``: when it arrived on this store's clock, if before now (a sample taken
        from a ring later, ``DrainedSubscriber.drain``); never later than now."""
        return self.put_many(((source, value, seq, arrived_s),)) == 1

    def put_many(self, items: Iterable[tuple[Hashable, T, int | None, float | None]]) -> int:
        """``put(source, value, seq=seq, arrived_s=arrived_s)`` for each item, under one lock
        and with one wake-up for all (e.g. every beacon of one relay); how many were stored."""
        stored = 0
        with self._cond:
            clock_s = self._clock()
            values = self._values
            for source, value, seq, arrived_s in items:
                old = values.get(source)
                if old is None and len(values) >= self._max_sources:
                    continue
                if old is not None and seq is not None and old[2] is not None and seq < old[2]:
                    continue
                values[source] = (value, clock_s if arrived_s is None
                                  else min(arrived_s, clock_s), seq)
                stored += 1
            if stored:
                self._cond.notify_all()
        return stored

    def get(self, source: Hashable) -> tuple[T, float] | None:
        """(value, age in seconds) or None if ``source`` never sent anything."""
        with self._cond:
            now = self._clock()
            entry = self._values.get(source)
        return None if entry is None else (entry[0], now - entry[1])

    def fresh(self, max_age_s: float) -> dict[Hashable, T]:
        """The values no older than ``max_age_s`` seconds, by source."""
        with self._cond:
            now = self._clock()
            return {s: v for s, (v, t, _) in self._values.items() if now - t <= max_age_s}

    def fresh_with_ages(self, max_age_s: float) -> dict[Hashable, tuple[T, float]]:
        """(value, age in seconds) of the values no older than ``max_age_s``, by source."""
        with self._cond:
            now = self._clock()
            return {s: (v, now - t) for s, (v, t, _) in self._values.items()
                    if now - t <= max_age_s}

    def ages(self) -> dict[Hashable, float]:
        with self._cond:
            now = self._clock()
            return {s: now - t for s, (_, t, _) in self._values.items()}

    def wait_for(self, sources: Iterable[Hashable], timeout_s: float, *,
                 min_seq: int | None = None) -> bool:
        """Block until every source in ``sources`` has a value (with ``seq >= min_seq`` if
        given); False at the deadline."""
        wanted = set(sources)

        def ready() -> bool:
            for s in wanted:
                entry = self._values.get(s)
                if entry is None or (min_seq is not None
                                     and (entry[2] is None or entry[2] < min_seq)):
                    return False
            return True

        with self._cond:
            return self._cond.wait_for(ready, timeout=timeout_s)

    def __len__(self) -> int:
        with self._cond:
            return len(self._values)


class StepMailbox(Generic[T]):
    """Thread-safe values keyed (step, round, sender) for lockstep consensus.

    - ``put`` keeps the FIRST value for a key; later duplicates are counted and ignored, so
      what ``wait_for`` returned can never change under the caller.
    - ``wait_for(step, round, senders, timeout_s)`` blocks on a condition variable until every
      requested sender has a value for (step, round) or the deadline passes, then returns
      exactly the requested senders that have one. ``put`` wakes a waiter only when its set
      is complete, not at every arrival (one wake-up per wait instead of one per sender).
    - Bounded memory: ``wait_for`` for step k drops every entry with a step below
      ``k - horizon_steps`` or above ``k + max_ahead_steps``, and ``put`` refuses such steps
      (and anything beyond ``max_entries``). Refusals are counted in ``refused``.
    """

    def __init__(self, *, horizon_steps: int = 2, max_ahead_steps: int = 4,
                 max_entries: int = 65536) -> None:
        for name, value in (("horizon_steps", horizon_steps),
                            ("max_ahead_steps", max_ahead_steps), ("max_entries", max_entries)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"StepMailbox: {name} must be an integer >= 0, got {value!r}")
        self.horizon_steps = horizon_steps
        self.max_ahead_steps = max_ahead_steps
        self.max_entries = max_entries
        self._cond = threading.Condition()
        self._boxes: dict[tuple[int, int], dict[int, T]] = {}
        self._entries = 0
        self._current: int | None = None  # the newest step anyone waited for
        self._closed = False
        self._waiters: dict[tuple[int, int], list[set[int]]] = {}  # what each wait needs
        self.refused = 0
        self.duplicates = 0

    def _in_window(self, step: int) -> bool:
        if self._current is None:
            return True
        return self._current - self.horizon_steps <= step <= self._current + self.max_ahead_steps

    def put(self, step: int, round: int, sender: int, value: T) -> bool:
        """Store ``value``; False if it was a duplicate or refused (outside the window, full)."""
        return self.put_many(((step, round, sender, value),)) == 1

    def put_many(self, items: Iterable[tuple[int, int, int, T]]) -> int:
        """``put(step, round, sender, value)`` for each item, under one lock, waking the
        waiters once (e.g. every beacon of one relay); how many were stored."""
        stored = 0
        complete = False
        with self._cond:
            for step, round, sender, value in items:
                if not self._in_window(step) or self._entries >= self.max_entries:
                    self.refused += 1
                    continue
                box = self._boxes.setdefault((step, round), {})
                if sender in box:
                    self.duplicates += 1
                    continue
                box[sender] = value
                self._entries += 1
                stored += 1
                complete = complete or any(
                    wanted <= box.keys() for wanted in self._waiters.get((step, round), ()))
            if complete:
                self._cond.notify_all()
        return stored

    def wait_for(self, step: int, round: int, senders: Iterable[int],
                 timeout_s: float) -> dict[int, T]:
        """What arrived for (step, round) from ``senders``: all of them, or what there is at
        the deadline or once ``close`` was called."""
        wanted = set(senders)
        deadline = time.monotonic() + max(0.0, timeout_s)
        key = (step, round)
        with self._cond:
            if self._current is None or step > self._current:
                self._current = step
                self._prune()
            waiters = self._waiters.setdefault(key, [])
            waiters.append(wanted)
            try:
                while True:
                    box = self._boxes.get(key, {})
                    found = {s: box[s] for s in wanted if s in box}
                    remaining = deadline - time.monotonic()
                    if len(found) == len(wanted) or remaining <= 0 or self._closed:
                        return found
                    self._cond.wait(remaining)
            finally:
                waiters.remove(wanted)
                if not waiters:
                    del self._waiters[key]

    def close(self) -> None:
        """From now on ``wait_for`` returns at once, including waits in progress (e.g. the
        mission ended: nothing more is coming)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def get(self, step: int, round: int) -> dict[int, T]:
        """What has arrived for (step, round) so far, without waiting (a copy)."""
        with self._cond:
            return dict(self._boxes.get((step, round), {}))

    def prune(self, current_step: int) -> None:
        """Advance the window to ``current_step`` without waiting."""
        with self._cond:
            if self._current is None or current_step > self._current:
                self._current = current_step
                self._prune()

    def _prune(self) -> None:
        for key in [k for k in self._boxes if not self._in_window(k[0])]:
            self._entries -= len(self._boxes.pop(key))

    def __len__(self) -> int:
        with self._cond:
            return self._entries


# -- subscriptions -------------------------------------------------------------------------------


def subscribe(
    session: zenoh.Session,
    key: str,
    decode: Callable[[bytes], T],
    on_value: Callable[[str, T], None],
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
    return DrainedSubscriber(session.declare_subscriber(
        key, zenoh.handlers.RingChannel(keep_latest), allowed_origin=origin), callback)


class DrainedSubscriber:
    """A subscriber whose samples wait inside zenoh until ``drain()``: in a ring, the oldest
    dropped when it is full (``subscribe(..., keep_latest=K)``), or in a FIFO on which
    zenoh's receiving waits when it is full (``subscribe(..., backlog=K)``).

    The ring, measured against its previous form (a Python thread of ours per ring running the
    callback as samples came) on Case 2 scaled to N = 12 in realtime (two 6 s runs each, side
    by side): 44.1 -> 7.4 % late steps, step time p99 26.3 -> 13.8 ms, neighbour age 9.4 ->
    6.0 ms. Every sample used to cost a thread wake-up and two GIL hand-overs, and preempted
    the agent's step when it came during one.

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
