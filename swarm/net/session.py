"""Zenoh sessions (SPEC §12): explicit-endpoint session configs, opening a session with a
one-line error, and the publishers the processes put through.

``zenoh_config`` builds a session config with explicit endpoints only: no multicast scouting
and no default listener (zenoh's own default listens on ``tcp/[::]:<port>`` on every
interface and scouts on UDP multicast 224.0.0.224:7446). A swarm started with loopback
endpoints therefore creates no traffic outside 127.0.0.0/8. With a ``TlsIdentity``
(``swarm.net.security``, the config's ``[security]``) every link is mutual TLS (``tls/...``
endpoints only), and a router can be given an ``access_control`` block to enforce.

The rest of the Zenoh layer: ``swarm.net.keys`` (the key space of a run),
``swarm.net.subscriptions`` (validated deliveries), ``swarm.net.stores`` (what an agent step
reads them from) and ``swarm.net.faults`` (a lossy or slow link, for tests).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final, Literal

import zenoh

from swarm.errors import UsageError, VigilError
from swarm.net.security import TlsIdentity

Mode = Literal["peer", "client", "router"]
MODES: Final = ("peer", "client", "router")
PROTOCOLS: Final = ("tcp", "udp", "tls")

_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                       r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
MAX_REASON_CHARS: Final = 300  # a reason in an error or a rejection line is cut to this
TX_DATA_QUEUE_BATCHES: Final = 16  # per link and priority; zenoh allocates batches lazily
# Zenoh's thread pools (its ZENOH_RUNTIME variable; the user's own setting wins). By default
# zenoh receives on two "rx" worker threads, accepts on "acc", manages links on "net", and a
# message handed from one pool to another wakes a thread of the other: on a 2-core machine,
# waking a thread costs the waker ~20 µs of CPU. Here receiving, accepting and link
# management run on zenoh's one "app" thread; transmission keeps its own thread, so that a
# put that waits for room in a full queue (congestion control "block": from a main thread, or
# from a subscription's own Python thread as the world's lockstep relay) always has a thread
# left to empty it. This about halves the context switches per simulated step (Case 2,
# lockstep: the world 74 → 41, each agent 18 → 10) and removes nearly all late steps of
# Case 2 scaled to N = 12 in realtime (~10 % → under 0.5 %).
# The price: one receiving thread per process. A router forwarding to a link whose queue is
# full (TX_DATA_QUEUE_BATCHES of up to 64 kB) waits on that thread until the link drains;
# if the process itself is that link's reader (a router and a client of it in one process:
# tests only, never the swarm's processes) it waits for itself until zenoh gives up (~5 s).
# A callback on the receiving thread (``subscribe(direct=True)``) must only store, never put.
ZENOH_RUNTIME_VARIABLE: Final = "ZENOH_RUNTIME"
ZENOH_RUNTIME_DEFAULT: Final = "(rx: (handover: app), acc: (handover: app), net: (handover: app))"


class TransportError(VigilError, RuntimeError):
    """A Zenoh session could not be opened (one line: what and why)."""


class EndpointError(UsageError, ValueError):
    """A Zenoh endpoint that cannot be used as given (``--listen``, ``--connect``): malformed,
    or plain where ``[security]`` wants TLS (or the other way round)."""


# -- configuration -------------------------------------------------------------------------------


def parse_endpoint(endpoint: str, *, role: Literal["listen", "connect"] = "connect"
                   ) -> tuple[str, str, int]:
    """Split ``"<tcp|udp|tls>/<host>:<port>"`` into (protocol, host, port), or raise
    ``EndpointError`` (a ``ValueError``).

    Hosts are IPv4 addresses, bracketed IPv6 addresses (``tcp/[::1]:7447``) or host names. Port
    0 (any free port) is allowed for ``listen`` only. Zenoh itself accepts malformed strings at
    configuration time and fails later, so every endpoint goes through here first.
    """
    if not isinstance(endpoint, str):
        raise EndpointError(f"zenoh {role} endpoint must be a string like "
                            f"'tcp/127.0.0.1:7447', got {type(endpoint).__name__}")
    shown = endpoint if len(endpoint) <= 80 else endpoint[:77] + "..."
    expected = "expected '<tcp|udp|tls>/<host>:<port>', e.g. 'tcp/127.0.0.1:7447'"
    proto, slash, rest = endpoint.partition("/")
    if not slash or proto not in PROTOCOLS:
        raise EndpointError(f"zenoh {role} endpoint {shown!r}: {expected}")
    host, colon, port_text = rest.rpartition(":")
    if not colon or not host or not port_text.isdigit() or len(port_text) > 5:
        raise EndpointError(f"zenoh {role} endpoint {shown!r}: {expected}")
    port = int(port_text)
    if not (0 if role == "listen" else 1) <= port <= 65535:
        raise EndpointError(f"zenoh {role} endpoint {shown!r}: port {port} out of range "
                            f"({'0' if role == 'listen' else '1'}-65535)")
    if host.startswith("[") and host.endswith("]"):
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            raise EndpointError(f"zenoh {role} endpoint {shown!r}: {host} is not an IPv6 "
                                "address") from None
    elif re.fullmatch(r"[0-9.]+", host):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise EndpointError(f"zenoh {role} endpoint {shown!r}: {host} is not an IPv4 "
                                "address") from None
    elif not _HOSTNAME.match(host):
        raise EndpointError(f"zenoh {role} endpoint {shown!r}: {host!r} is not a host "
                            f"name; {expected}")
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
    """``EndpointError`` unless every endpoint is ``tls/...`` with TLS on, and none is
    without."""
    for endpoint in endpoints:
        if endpoint.startswith("tls/") != tls:
            raise EndpointError(f"zenoh endpoint {endpoint[:80]!r}: " + (
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
        # truth, clock) toward one subscriber overflows it whenever the link's tx task is not
        # scheduled within wait_before_drop (1 ms) on a loaded machine, and droppable
        # (realtime) messages are lost (~10 % of the truth toward a recording launcher).
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
        raise TransportError(f"cannot open zenoh session: {message[:MAX_REASON_CHARS]}"
                             ) from None


def join_router(endpoints: Sequence[str], timeout_s: float, *, mode: Mode = "client",
                listen: Sequence[str] = (), tls: TlsIdentity | None = None,
                connect_timeout_s: float | None = None, retry_s: float = 0.1,
                before_each_try: Callable[[], None] = lambda: None,
                on_wait: Callable[[], None] = lambda: None,
                pause: Callable[[float], Any] = time.sleep) -> zenoh.Session:
    """A session (a client by default) on the router at ``endpoints``, tried every ``retry_s``
    (``pause``) until ``timeout_s`` has passed; then the last ``TransportError``. Every
    process of the swarm joins the world's router this way, since the world may still be
    starting. ``before_each_try`` may raise to give up sooner (the launcher: a child died);
    ``on_wait`` is called once, after the first try that failed (a process says it waits)."""
    deadline = time.monotonic() + timeout_s
    waited = False
    while True:
        before_each_try()
        try:
            return open_session(zenoh_config(mode=mode, listen=listen, connect=list(endpoints),
                                             connect_timeout_s=connect_timeout_s, tls=tls))
        except TransportError:
            if time.monotonic() > deadline:
                raise
        if not waited:
            waited = True
            on_wait()
        pause(retry_s)


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
    agent) goes out in fewer writes (a lockstep of the swarm's messages without its compute, 6
    agents on 2 cores: 4.5 instead of 5.3 ms per step, ~20 % less router CPU).
    """
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        express=express,
    )
