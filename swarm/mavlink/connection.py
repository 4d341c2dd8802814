"""Opening an agent's MAVLink connection (pymavlink, MAVLink 2, ardupilotmega), and adopting
the ``udpin`` socket ``swarm-agent`` bound before its imports (``swarm.mavlink.udpin``).

This module imports the standard library and pymavlink only.
"""

from __future__ import annotations

import os
import socket
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.errors import VigilError
from swarm.mavlink.udpin import BoundSocket, udpin_address


class LinkError(VigilError, RuntimeError):
    """The autopilot link failed; the message is one line saying what to check."""


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def check_udpin_port_free(url: str) -> None:
    """pymavlink binds udpin sockets with SO_REUSEADDR, so on Linux a second process can bind
    the same port silently and steal datagrams. Probe with a plain bind first."""
    address = udpin_address(url)
    if address is None or address[1] == 0:
        return
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind(address)
    except OSError as exc:
        raise LinkError(one_line(
            f"cannot listen on {url}: {exc.strerror or exc}: is another agent (same --id and "
            f"--mavlink-base) or a ground station already using that port?")) from exc
    finally:
        probe.close()


def open_connection(url: str, source_system: int, *, who: str,
                    bound: BoundSocket | None = None) -> Any:
    """The pymavlink connection (a ``mavfile``) for ``url`` (MAVLink 2, ardupilotmega
    dialect), sending as system ``source_system``, component MAV_COMP_ID_ONBOARD_COMPUTER (a
    companion computer); ``LinkError`` (one line, starting with ``who``) if the port is taken
    or pymavlink cannot open it.

    ``bound``: a socket already bound to ``url`` (``swarm.mavlink.udpin.bind_udpin``), which
    the connection takes over with whatever it has queued. pymavlink binds a udpin socket of
    its own when it opens one, so it opens on an ephemeral port of the same host and its
    descriptor is then pointed at ``bound``'s socket (``dup2``): every read, write and
    ``getsockname`` goes to the socket bound first."""
    if bound is not None:
        if bound.url != url:
            raise ValueError(f"{who}: the bound socket is {bound.url}, not {url}")
        url_opened = f"udpin:{bound.sock.getsockname()[0]}:0"
    else:
        check_udpin_port_free(url)
        url_opened = url
    # pymavlink picks MAVLink 1 or 2 from this variable when the connection sets its
    # dialect (it is read at connection time, and inherited by child processes).
    os.environ.setdefault("MAVLINK20", "1")
    try:
        conn: Any = mavutil.mavlink_connection(
            url_opened, source_system=source_system,
            source_component=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
            dialect="ardupilotmega", udp_timeout=5.0)
    except Exception as exc:
        raise LinkError(one_line(f"{who}: cannot open MAVLink connection {url!r}: {exc}")
                        ) from exc
    if bound is not None:
        # Same family and type, non-blocking already (a property of the socket, which the dup
        # shares); not inherited by child processes, as pymavlink's own.
        os.dup2(bound.sock.fileno(), conn.port.fileno(), inheritable=False)
        bound.close()
    if not conn.mavlink20():
        conn.close()
        raise LinkError(f"{who}: pymavlink did not select MAVLink 2 for "
                        f"{url} (MAVLINK20={os.environ.get('MAVLINK20')!r})")
    return conn
