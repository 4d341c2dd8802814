"""UDP socket of one emulated vehicle, served the way PX4 SITL serves its offboard link.

The vehicle binds a local address (default ``127.0.0.1:0``: a port from the OS) and sends
to the agent's address (``127.0.0.1:(base + i)``, where the agent listens with pymavlink
``udpin:``). Like PX4 SITL it then replies to whoever talks to it: the peer address follows
the sender of the latest datagram that starts like a MAVLink frame (first byte 0xFD or 0xFE),
so a tool relaying the link (MAVProxy, mavlink-router) is followed, while a stray sender of
junk does not take the link over. The endpoint never parses MAVLink (EmulatedVehicle does).

Public API
----------
``VehicleEndpoint(peer_address, *, bind_address=("127.0.0.1", 0), follow_sender=True)``
``local_address`` / ``peer_address`` (properties, (host, port)),
``send(packets, *, coalesce=False) -> int`` (datagrams sent; each packet is a datagram unless
``coalesce``; OS errors such as "connection refused" while the agent is not up yet are
counted in ``send_errors``, never raised), ``poll(max_datagrams=1024) -> list[bytes]``
(non-blocking; every datagram waiting now, oldest first), ``poll_from(max_datagrams=1024)
-> list[(bytes, sender, age_s)]`` (the same, but never follows the sender: the caller
``follow(sender)``s only a sender whose frame the vehicle took, so junk cannot redirect the
vehicle's stream; ``age_s``: how long ago the kernel received the datagram, from its
SO_TIMESTAMPNS stamp, 0 where there is none), ``fileno()`` (for selectors),
``close()`` (idempotent; also a context manager). Counters: ``datagrams_sent``,
``datagrams_received``, ``send_errors``, ``receive_errors``, ``peer_changes``.
"""

from __future__ import annotations

import socket
import struct
import sys
import time
from collections.abc import Iterable
from types import TracebackType

__all__ = ["VehicleEndpoint"]

_MAX_DATAGRAM = 65535
_MAVLINK_MAGIC = (0xFD, 0xFE)  # MAVLink 2, MAVLink 1 start-of-frame markers
# Linux: each datagram's arrival time (CLOCK_REALTIME) as a struct timespec in its ancillary
# data. Elsewhere datagrams have no stamp and count as just arrived.
# Python does not name the option; 35 is its number in Linux's generic ABI (x86, arm, ...).
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS",
                          35 if sys.platform.startswith("linux") else None)
_TIMESPEC = struct.Struct("@ll")  # struct timespec: tv_sec, tv_nsec
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0


class VehicleEndpoint:
    """Non-blocking UDP endpoint of one vehicle (see module docstring)."""

    def __init__(
        self,
        peer_address: tuple[str, int],
        *,
        bind_address: tuple[str, int] = ("127.0.0.1", 0),
        follow_sender: bool = True,
    ) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setblocking(False)
            self._sock.bind(bind_address)
            if _SO_TIMESTAMPNS is not None:
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            self._sock.close()
            raise
        self._peer: tuple[str, int] = (str(peer_address[0]), int(peer_address[1]))
        self._follow = follow_sender
        self._closed = False
        self.datagrams_sent = 0
        self.datagrams_received = 0
        self.send_errors = 0
        self.receive_errors = 0
        self.peer_changes = 0

    @property
    def local_address(self) -> tuple[str, int]:
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def peer_address(self) -> tuple[str, int]:
        return self._peer

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, packets: Iterable[bytes], *, coalesce: bool = False) -> int:
        chunks = [bytes(p) for p in packets if p]
        if coalesce and chunks:
            chunks = [b"".join(chunks)]
        sent = 0
        for chunk in chunks:
            try:
                self._sock.sendto(chunk, self._peer)
                sent += 1
            except OSError:  # ECONNREFUSED from an earlier ICMP, ENOBUFS, EAGAIN, ...
                self.send_errors += 1
        self.datagrams_sent += sent
        return sent

    def poll(self, max_datagrams: int = 1024) -> list[bytes]:
        out: list[bytes] = []
        while len(out) < max_datagrams:
            try:
                data, sender = self._sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ECONNREFUSED reported for an earlier send
                self.receive_errors += 1
                break
            self.datagrams_received += 1
            if self._follow and data and data[0] in _MAVLINK_MAGIC:
                peer = (str(sender[0]), int(sender[1]))
                if peer != self._peer:
                    self._peer = peer
                    self.peer_changes += 1
            out.append(data)
        return out

    def poll_from(self, max_datagrams: int = 1024
                  ) -> list[tuple[bytes, tuple[str, int], float]]:
        """Like ``poll`` with each datagram's sender and age [s], and the peer left alone.

        The age lets a caller that was held up (a stall of its loop) handle each datagram at
        the time it arrived: an autopilot's failsafe timer sees the setpoint stream as the
        vehicle would have, not as late as the emulator got round to reading it."""
        out: list[tuple[bytes, tuple[str, int], float]] = []
        while len(out) < max_datagrams:
            try:
                data, ancillary, _flags, sender = self._sock.recvmsg(_MAX_DATAGRAM,
                                                                    _ANCILLARY_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.receive_errors += 1
                break
            self.datagrams_received += 1
            age = 0.0
            for level, kind, payload in ancillary:
                if (level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS
                        and len(payload) >= _TIMESPEC.size):
                    seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
                    age = max(time.time() - (seconds + 1e-9 * nanoseconds), 0.0)
            out.append((data, (str(sender[0]), int(sender[1])), age))
        return out

    def follow(self, sender: tuple[str, int]) -> None:
        """Send to ``sender`` from now on."""
        peer = (str(sender[0]), int(sender[1]))
        if peer != self._peer:
            self._peer = peer
            self.peer_changes += 1

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()

    def __enter__(self) -> VehicleEndpoint:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
