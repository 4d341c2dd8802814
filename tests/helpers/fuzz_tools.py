"""Bad input for the process swarm (tests/launch/test_fuzz.py): payload generators and flooders.

Every generator is seeded and keeps only inputs whose fate is known in advance, decided by
the receiving code itself:

- Zenoh: ``zenoh_payloads`` keeps a payload only if the codec the agents use
  (``WireCodec.decode_*``) refuses it, so each one is exactly one counted rejection at each
  subscriber it reaches. Kinds: random bytes of random lengths, random msgpack structures
  (some with the right kind tag and version in front), and mutations of real valid messages
  (bit flips, truncation, extension, another kind's tag, wrong versions, out-of-range ids and
  steps, wrong shapes and lengths, NaN/±inf in every float field and packed float array,
  fields dropped or added) plus a few payloads over the 1 MiB limit.
- MAVLink: ``mavlink_datagrams`` makes random datagrams and corrupted MAVLink 2 (and 1)
  frames (bad CRC, bad length, unknown message ids, truncated, extended, bit flips, the
  signed flag without a signature, NaN/±inf in LOCAL_POSITION_NED and
  SET_POSITION_TARGET_LOCAL_NED with a valid CRC). ``VehicleModel`` replays each datagram on
  an ``EmulatedVehicle`` of the same flavour and keeps it only if the vehicle rejects all of
  it (nothing taken, nothing ignored, no reply), recording how many rejections it makes.

``UdpFlood`` sends datagrams to UDP ports without ever overflowing the receiver's socket
buffer (a drop would make counts inexact): it sends a port its next burst only once
``/proc/net/udp`` shows that socket's queue empty, and reports the kernel's drop counters.
"""

from __future__ import annotations

import math
import os
import random
import socket
import struct
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import msgspec
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.vehicle import EmulatedVehicle
from swarm.messages.wire import DEFAULT_MAX_PAYLOAD_BYTES, WireError

NONFINITE = (math.nan, -math.nan, math.inf, -math.inf)
# NaN payloads beyond the canonical one: signalling, negative, all-ones mantissa.
_NONFINITE_BYTES = (*(struct.pack("<d", v) for v in NONFINITE),
                    struct.pack("<Q", 0x7FF0000000000001), struct.pack("<Q", 0xFFFFFFFFFFFFFFFF))
_KINDS = ("consensus", "beacon", "beacons", "camera", "truth", "clock", "telemetry")


# -- Zenoh payloads --------------------------------------------------------------------------


def random_msgpack(rng: random.Random, depth: int = 0) -> Any:
    """A random msgpack-encodable value (nested up to a few levels)."""
    pick = rng.randrange(12 if depth < 3 else 8)
    if pick == 0:
        return rng.choice((None, True, False))
    if pick == 1:
        return rng.randint(-(2 ** 63), 2 ** 64 - 1)
    if pick == 2:
        return rng.randint(-40, 40)
    if pick == 3:
        return rng.choice((*NONFINITE, 0.0, -0.0, 5e-324, 1.7976931348623157e308,
                           rng.uniform(-1e6, 1e6)))
    if pick == 4:
        return "".join(chr(rng.randrange(0x20, 0x2FFF)) for _ in range(rng.randrange(12)))
    if pick == 5:
        return rng.choice(_KINDS)
    if pick in (6, 7):
        return rng.randbytes(rng.choice((0, 1, 7, 8, 24, 48, 96, rng.randrange(600))))
    if pick in (8, 9, 10):
        return [random_msgpack(rng, depth + 1) for _ in range(rng.randrange(9))]
    return {str(random_msgpack(rng, 3))[:8]: random_msgpack(rng, depth + 1)
            for _ in range(rng.randrange(4))}


def _leaves(value: Any, path: tuple[int, ...] = ()) -> list[tuple[tuple[int, ...], Any]]:
    """Every (path, value) of a decoded msgpack tree of lists, the lists themselves included."""
    out = [(path, value)]
    if isinstance(value, list):
        for k, item in enumerate(value):
            out += _leaves(item, (*path, k))
    return out


def _replace(tree: Any, path: tuple[int, ...], new: Any) -> Any:
    if not path:
        return new
    copy = list(tree)
    copy[path[0]] = _replace(copy[path[0]], path[1:], new)
    return copy


def _inject_nonfinite(rng: random.Random, data: bytes) -> bytes:
    """One float64 of a packed array (length a multiple of 8) made NaN or ±inf."""
    if len(data) < 8 or len(data) % 8:
        return data + rng.choice(_NONFINITE_BYTES)
    k = 8 * rng.randrange(len(data) // 8)
    return data[:k] + rng.choice(_NONFINITE_BYTES) + data[k + 8:]


def _mutate_leaf(rng: random.Random, value: Any, n_drones: int) -> Any:
    if isinstance(value, bool) or value is None:
        return rng.choice((0, 1, "true", None, [], 2.5))
    if isinstance(value, int):
        return rng.choice((-1, -(2 ** 63), 2 ** 64 - 1, 2 ** 31, n_drones, n_drones + 7,
                           1024, 1025, value + 1.5, float(value), True, None, str(value)))
    if isinstance(value, float):
        return rng.choice((*NONFINITE, -1.0, -5e-324, 1e300, "1.0", None, [value],
                           int(value) if math.isfinite(value) else 0))
    if isinstance(value, str):
        return rng.choice(("", "x" * rng.choice((65, 513, 4000)), value + "\x00", "é" * 70, 7,
                           None, rng.choice(_KINDS)))
    if isinstance(value, bytes):
        ops = (
            lambda: _inject_nonfinite(rng, value),
            lambda: value[:rng.randrange(max(len(value), 1))],
            lambda: value + rng.randbytes(rng.choice((1, 7, 8, 64))),
            lambda: b"",
            lambda: list(value[:16]),
        )
        return rng.choice(ops)()
    if isinstance(value, list):
        ops = (
            lambda: value[:-1],
            lambda: [*value, random_msgpack(rng, 2)],
            lambda: value + value,
            lambda: [],
            lambda: [rng.randint(0, 2 ** 20) for _ in range(rng.randrange(6))],
            lambda: dict(enumerate(value)),
        )
        return rng.choice(ops)()
    return random_msgpack(rng)


def _structural(rng: random.Random, base: bytes, n_drones: int) -> bytes:
    tree = msgspec.msgpack.decode(base)
    pick = rng.randrange(6)
    if pick == 0:  # another kind's tag, or no known tag
        other = rng.choice([k for k in (*_KINDS, "", "CONSENSUS", 7) if k != tree[0]])
        tree = [other, *tree[1:]]
    elif pick == 1:  # another wire version
        tree = [tree[0], rng.choice((0, 1, 2, 4, 99, -1, "3", 3.0, None)), *tree[2:]]
    elif pick == 2:  # a field missing
        tree = tree[:rng.randrange(len(tree))]
    elif pick == 3:  # fields added
        tree = [*tree, *(random_msgpack(rng, 2) for _ in range(rng.randrange(1, 4)))]
    elif pick == 4:  # a dict instead of an array
        tree = {str(k): v for k, v in enumerate(tree)}
    else:  # a non-finite number in a float or packed float field
        candidates = [(p, v) for p, v in _leaves(tree)
                      if isinstance(v, bytes) or (isinstance(v, float) and not isinstance(v, bool))]
        if candidates:
            path, value = rng.choice(candidates)
            new = (_inject_nonfinite(rng, value) if isinstance(value, bytes)
                   else rng.choice(NONFINITE))
            tree = _replace(tree, path, new)
    return msgspec.msgpack.encode(tree)


def _bytewise(rng: random.Random, base: bytes) -> bytes:
    data = bytearray(base)
    pick = rng.randrange(4)
    if pick == 0:  # bit flips
        for _ in range(rng.randint(1, 8)):
            k = rng.randrange(len(data))
            data[k] ^= 1 << rng.randrange(8)
        return bytes(data)
    if pick == 1:  # truncation
        return bytes(data[:rng.randrange(len(data))])
    if pick == 2:  # extension
        return bytes(data) + rng.randbytes(rng.randint(1, 64))
    k = rng.randrange(len(data))  # a random splice
    return bytes(data[:k]) + rng.randbytes(rng.randint(1, 16)) + bytes(data[k + 1:])


def _random_bytes(rng: random.Random) -> bytes:
    size = rng.choice((0, 1, 2, 3, 5, 8, 16, 31, 64, 100, rng.randrange(300),
                       rng.randrange(300), rng.randrange(4096)))
    data = rng.randbytes(size)
    if data and rng.random() < 0.3:  # a msgpack array header in front
        data = bytes((0x90 | rng.randrange(16),)) + data[1:]
    return data


def zenoh_payloads(rng: random.Random, bases: list[bytes], decode: Callable[[bytes], Any],
                   count: int, *, n_drones: int, oversized: int = 2) -> list[bytes]:
    """``count`` payloads that ``decode`` refuses with ``WireError`` (``oversized`` of them
    over the codec's 1 MiB limit), the rest a mix of the kinds in the module docstring built
    from the valid encoded messages ``bases``."""
    out: list[bytes] = []
    for k in range(oversized):
        out.append(bases[k % len(bases)] + rng.randbytes(DEFAULT_MAX_PAYLOAD_BYTES))
    attempts = 0
    while len(out) < count:
        attempts += 1
        if attempts > 20 * count:
            raise RuntimeError(f"only {len(out)} of {count} rejected payloads after "
                               f"{attempts} attempts")
        base = rng.choice(bases)
        pick = rng.random()
        if pick < 0.2:
            payload = _random_bytes(rng)
        elif pick < 0.35:
            value = random_msgpack(rng)
            if rng.random() < 0.5:
                head = msgspec.msgpack.decode(base)[:2]
                value = [*head, *(random_msgpack(rng, 1) for _ in range(rng.randrange(9)))]
            payload = msgspec.msgpack.encode(value)
        elif pick < 0.6:
            tree = msgspec.msgpack.decode(base)
            path, value = rng.choice(_leaves(tree)[1:])
            payload = msgspec.msgpack.encode(
                _replace(tree, path, _mutate_leaf(rng, value, n_drones)))
        elif pick < 0.8:
            payload = _structural(rng, base, n_drones)
        else:
            payload = _bytewise(rng, base)
        try:
            decode(payload)
        except WireError:
            out.append(payload)
    rng.shuffle(out)
    return out


# -- MAVLink datagrams -----------------------------------------------------------------------


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


def _encoder(sysid: int, compid: int) -> tuple[mav.MAVLink, _Sink]:
    sink = _Sink()
    return mav.MAVLink(sink, srcSystem=sysid, srcComponent=compid), sink


def _frame(encoder: tuple[mav.MAVLink, _Sink], message: Any) -> bytes:
    link, sink = encoder
    link.send(message)
    return sink.frames.pop()


def valid_frames(rng: random.Random, sysid: int) -> list[bytes]:
    """Valid MAVLink 2 frames as an agent or a vehicle of system ``sysid`` sends them, each
    addressed (where it has a target) to the broadcast system 0, so that any vehicle of the
    swarm treats their corrupted versions alike."""
    agent = _encoder(sysid, mav.MAV_COMP_ID_ONBOARD_COMPUTER)
    vehicle = _encoder(sysid, 1)
    v = [rng.uniform(-3, 3) for _ in range(3)]
    return [
        _frame(agent, agent[0].set_position_target_local_ned_encode(
            rng.randrange(2 ** 32), 0, 1, mav.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, *v,
            0, 0, 0, 0, 0)),
        _frame(agent, agent[0].command_long_encode(0, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)),
        _frame(agent, agent[0].heartbeat_encode(18, 8, 0, 0, 4)),
        _frame(agent, agent[0].param_set_encode(0, 1, b"COM_OF_LOSS_T", 0.5, 9)),
        _frame(vehicle, vehicle[0].local_position_ned_encode(
            rng.randrange(2 ** 32), *(rng.uniform(-50, 50) for _ in range(6)))),
        _frame(vehicle, vehicle[0].heartbeat_encode(2, 12, 129, 6 << 16, 4, 3)),
        _frame(vehicle, vehicle[0].command_ack_encode(400, 0, 0, 0, 0, 0)),
    ]


def _nonfinite_frame(rng: random.Random, sysid: int) -> bytes:
    """A valid-CRC setpoint or position report with NaN/±inf in a float field."""
    values = [rng.uniform(-3, 3) for _ in range(6)]
    values[rng.randrange(6)] = rng.choice(NONFINITE)
    if rng.random() < 0.5:
        agent = _encoder(sysid, mav.MAV_COMP_ID_ONBOARD_COMPUTER)
        target = rng.choice((0, 200))  # broadcast, or nobody: rejected either way
        return _frame(agent, agent[0].set_position_target_local_ned_encode(
            rng.randrange(2 ** 32), target, rng.choice((0, 1)), mav.MAV_FRAME_LOCAL_NED,
            0x0DC7, 0, 0, 0, *values[3:], 0, 0, 0, 0, 0))
    vehicle = _encoder(sysid, 1)
    return _frame(vehicle, vehicle[0].local_position_ned_encode(rng.randrange(2 ** 32),
                                                                *values))


def _recrc(frame: bytearray, crc_extra: int) -> None:
    """Recompute a MAVLink 2 frame's checksum (unsigned, length as in its header)."""
    end = 10 + frame[1]
    crc = mav.x25crc(bytes(frame[1:end]))
    crc.accumulate(bytes((crc_extra,)))
    frame[end:end + 2] = struct.pack("<H", crc.crc)


def _corrupt(rng: random.Random, frame: bytes) -> bytes:
    data = bytearray(frame)
    pick = rng.randrange(10)
    if pick == 0:  # bad CRC
        data[-1 - rng.randrange(2)] ^= 1 + rng.randrange(255)
    elif pick == 1:  # bad length
        data[1] = (data[1] + rng.choice((-3, -1, 1, 2, 40, 200))) % 256
    elif pick == 2:  # an unknown message id (with a checksum that would fit it)
        data[7:10] = rng.choice((0xFFFFFF, 0x0ABCDE, 0x00FF00, 60000)).to_bytes(3, "little")
        _recrc(data, rng.randrange(256))
    elif pick == 3:  # truncated
        data = data[:rng.randrange(1, len(data))]
    elif pick == 4:  # junk after the frame
        data += rng.randbytes(rng.randint(1, 40))
    elif pick == 5:  # bit flips
        for _ in range(rng.randint(1, 4)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    elif pick == 6:  # "signed" without a signature
        data[2] |= 0x01
    elif pick == 7:  # MAVLink 1 magic on a MAVLink 2 body
        data[0] = 0xFE
    elif pick == 8:  # a corrupted frame behind a good one (the datagram is still bad)
        tail = bytearray(frame)
        tail[-1] ^= 0x5A
        data = bytearray(frame) + tail
        return bytes(data)
    else:  # payload bytes changed, checksum left as it was
        k = 10 + rng.randrange(max(data[1], 1))
        if k < len(data) - 2:
            data[k] ^= 0xFF
        else:
            data[-2] ^= 0xFF
    return bytes(data)


def mavlink_datagrams(rng: random.Random, count: int, sysids: Iterable[int], *,
                      keep: Callable[[bytes], bool] = lambda _d: True,
                      huge: int = 3) -> list[bytes]:
    """``count`` datagrams that ``keep`` accepts: random bytes (``huge`` of them 20-64 kB),
    random bytes behind a MAVLink magic byte, corrupted valid frames of the given systems, and
    valid-CRC frames with NaN/±inf in their float fields."""
    sysids = list(sysids)
    frames = [f for s in sysids for f in valid_frames(rng, s)]
    out: list[bytes] = []
    for _ in range(huge):
        data = rng.randbytes(rng.randrange(20_000, 65_507))
        if keep(data):
            out.append(data)
    attempts = 0
    while len(out) < count:
        attempts += 1
        if attempts > 20 * count:
            raise RuntimeError(f"only {len(out)} of {count} datagrams kept")
        pick = rng.random()
        if pick < 0.25:
            data = _random_bytes(rng)
        elif pick < 0.35:
            data = bytes((rng.choice((0xFD, 0xFE)),)) + rng.randbytes(rng.randrange(300))
        elif pick < 0.85:
            data = _corrupt(rng, rng.choice(frames))
        else:
            data = _nonfinite_frame(rng, rng.choice(sysids))
        if keep(data):
            out.append(data)
    rng.shuffle(out)
    return out


class VehicleModel:
    """Decides a datagram's fate at an emulated vehicle: ``rejections(datagram)`` is the
    number of rejections it makes there if the vehicle rejects all of it (takes nothing,
    ignores nothing, replies nothing), else None. Rejections of such datagrams do not depend
    on the vehicle's state or id (every frame here is addressed to system 0 or to nobody)."""

    def __init__(self, flavour: str = "px4") -> None:
        self.vehicle = EmulatedVehicle(0, flavour, (0.0, 0.0, 3.0), (0.0, 0.0, 0.0))
        self.expected: dict[bytes, int] = {}

    def rejections(self, data: bytes) -> int | None:
        v = self.vehicle
        before = (v.rejected_frames, v.accepted_frames, v.ignored_messages)
        replies = v.receive(data, 1.0)
        rejected = v.rejected_frames - before[0]
        if replies or (v.accepted_frames, v.ignored_messages) != before[1:] or rejected < 1:
            return None
        return rejected

    def keep(self, data: bytes) -> bool:
        count = self.rejections(data)
        if count is None:
            return False
        self.expected[data] = count
        return True


# -- UDP flooding without loss ---------------------------------------------------------------


@dataclass
class UdpSocketState:
    port: int
    rx_queue: int
    drops: int
    inode: int


def udp_sockets() -> list[UdpSocketState]:
    """IPv4 UDP sockets bound to 127.0.0.1 (``/proc/net/udp``)."""
    out = []
    with open("/proc/net/udp") as table:
        next(table)
        for line in table:
            fields = line.split()
            host, port = fields[1].split(":")
            if host != "0100007F":
                continue
            rx_queue = int(fields[4].split(":")[1], 16)
            out.append(UdpSocketState(int(port, 16), rx_queue, int(fields[12]),
                                      int(fields[9])))
    return out


def socket_inodes(pid: int) -> set[int]:
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(int(target[8:-1]))
    return inodes


class UdpFlood:
    """Sends each port its datagrams in bursts (``burst`` datagrams, at most ``burst_bytes``),
    the next burst only once that port's socket queue is empty: the receiver never drops."""

    def __init__(self, plan: dict[int, list[bytes]], *, senders: int = 4,
                 burst: int = 32, burst_bytes: int = 48_000) -> None:
        self.pending = {port: deque(datagrams) for port, datagrams in plan.items()}
        self.sent = dict.fromkeys(plan, 0)
        self.burst, self.burst_bytes = burst, burst_bytes
        self.sockets = []
        for _ in range(senders):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            self.sockets.append(sock)
        self.drops_before = self.drops()

    def drops(self) -> dict[int, int]:
        by_port = {s.port: s.drops for s in udp_sockets()}
        return {port: by_port.get(port, -1) for port in self.pending}

    def run(self, deadline: float, stop: Callable[[], bool] = lambda: False) -> None:
        k = 0
        while any(self.pending.values()):
            if time.monotonic() > deadline or stop():
                raise TimeoutError(f"UDP flood unfinished: "
                                   f"{ {p: len(q) for p, q in self.pending.items()} }")
            queues = {s.port: s.rx_queue for s in udp_sockets()}
            progressed = False
            for port, queue in self.pending.items():
                if not queue or queues.get(port, 0) != 0:
                    continue
                size = 0
                for _ in range(self.burst):
                    if not queue or (size and size + len(queue[0]) > self.burst_bytes):
                        break
                    data = queue.popleft()
                    size += len(data) + 256
                    self.sockets[k % len(self.sockets)].sendto(data, ("127.0.0.1", port))
                    k += 1
                    self.sent[port] += 1
                progressed = True
            if not progressed:
                time.sleep(0.0005)  # poll the receivers' queues again (bounded by deadline)

    def close(self) -> None:
        for sock in self.sockets:
            sock.close()
