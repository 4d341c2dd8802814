"""An agent's ``udpin`` MAVLink socket, bound before anything else in its process.

``AutopilotLink`` (``swarm.mavlink.link``) sends no command that arms or moves the vehicle
before it has listened on its port for ``EXCLUSIVE_LISTEN_S``, counted from the moment its
socket was bound, so that a second autopilot on the port is heard first. A bound socket hears:
datagrams that arrive while the process is still busy wait in the kernel and are read, and
judged, by the link later. ``swarm-agent`` therefore binds its ``udpin`` socket here first,
before it imports pymavlink, numpy, the core and Zenoh (in a 6-drone launch on two cores,
~1 s of wall time that the listening window now overlaps instead of following), and the link
adopts the socket (``swarm.mavlink.connection.open_connection(..., bound=...)``).

Standard library only: this is all the process has loaded when it binds.
"""

from __future__ import annotations

import argparse
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass

# Emulated vehicle i talks to agent i on UDP DEFAULT_MAVLINK_BASE + i. Clear of every port
# autopilot SITL uses by default (PX4: 14540-14549 offboard, 14550 GCS, 14580+, 18570+,
# 13030+, 14030+, 19410+; ArduPilot: TCP 5760+, UDP 5501+, 9002+, MAVProxy 14550/14551), so
# that an emulated run never hears a real autopilot of the same machine, and below Linux's
# ephemeral ports (32768+).
DEFAULT_MAVLINK_BASE = 24540


def udpin_address(url: str) -> tuple[str, int] | None:
    """(host, port) of a ``udpin:HOST:PORT`` URL; None for any other URL."""
    if not url.startswith("udpin:"):
        return None
    host, _, port = url[len("udpin:"):].rpartition(":")
    try:
        return host, int(port)
    except ValueError:
        return None


@dataclass(frozen=True)
class BoundSocket:
    """A UDP socket bound to ``url``'s address at ``bound_s`` (``time.monotonic``)."""

    url: str
    sock: socket.socket
    bound_s: float

    def close(self) -> None:
        self.sock.close()  # harmless once the connection that adopted it closed it


def bind_udpin(url: str) -> BoundSocket:
    """Bind a non-blocking UDP socket to ``url`` (``udpin:HOST:PORT``, port > 0); OSError if
    the port is taken. No SO_REUSEADDR: a second process cannot share the port with it."""
    address = udpin_address(url)
    if address is None or address[1] <= 0:
        raise ValueError(f"not a udpin URL with a port: {url!r}")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(address)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return BoundSocket(url, sock, time.monotonic())


def bind_early(argv: Sequence[str]) -> BoundSocket | None:
    """``swarm-agent``'s ``udpin`` socket bound from its command line (``--id``,
    ``--mavlink``), or None: no usable ``--id``, a URL other than ``udpin:``, or a port that
    cannot be bound (the link then opens its connection itself and says what fails, as it
    would without this)."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--id", type=int)
    parser.add_argument("--mavlink")
    try:
        args, _ = parser.parse_known_args(list(argv))
    except SystemExit:  # argparse's way of refusing; the full parser will say why
        return None
    if args.id is None or not 0 <= args.id <= 253:
        return None
    url = args.mavlink or f"udpin:127.0.0.1:{DEFAULT_MAVLINK_BASE + args.id}"
    address = udpin_address(url)
    if address is None or address[1] <= 0:
        return None
    try:
        return bind_udpin(url)
    except OSError:
        return None
