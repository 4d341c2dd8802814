"""Bytes ↔ MAVLink messages for both ends of a link, with every bad frame counted.

The agent's autopilot link (``swarm.mavlink.link``) and the emulated vehicle
(``sim_world.vehicle``) parse the same way: pymavlink with robust parsing turns junk, bad
CRCs and bad lengths into BAD_DATA and frames of messages outside the dialect into
UNKNOWN_<id>; those are counted by reason and dropped. Over UDP a frame never spans two
datagrams, so bytes left in the parser after a datagram are a truncated frame: counted and
dropped, or they would swallow the start of the next valid frame.

Console text is not a bad frame: ArduPilot's console is also its first MAVLink port
(SERIAL0), and it prints there while it boots (its gyro calibration: "Init Gyro", a "*" per
round, a newline). pymavlink returns such a run of printable ASCII between frames as one
BAD_DATA ("Bad prefix"); ``console_text`` tells it from junk and broken frames (every
frame's header holds bytes outside printable ASCII: its magic byte and flags), and a caller
that expects console text hands ``parse_bytes`` a buffer for it instead of having it counted.

Fast path for the two messages of every control step, LOCAL_POSITION_NED (vehicle → agent)
and SET_POSITION_TARGET_LOCAL_NED (agent → vehicle): ``FastFrame`` packs and unpacks their
payloads with pymavlink's own struct formats and CRC extras and its sequence counter, and
frames them in one compiled call each (``swarm/mavlink/_frame.c``: header, truncation,
checksum), without pymavlink's byte-by-byte parser and per-message objects (which matters at
50 Hz × N drones on a small machine). Its frames are byte-identical to pymavlink's (tested).
It takes only exactly one unsigned MAVLink 2 frame of its message with a valid checksum
(``unpack`` returns None for anything else, and the caller hands those bytes to
``parse_bytes``), so bad frames are counted exactly as before.

MAVLink 2 signing (``swarm.mavlink.signing``): with a secret key on the parser, pymavlink
refuses unsigned, wrongly signed and replayed frames; ``parse_bytes`` counts them as
``unsigned``, ``bad_signature`` or ``stale_signature`` (timestamp not newer than the
stream's last one, pymavlink's replay rule). The fast path never applies then: ``pack``
leaves signing to pymavlink and callers must not ``unpack`` on a signed link (it would take
an unsigned frame). One repair: pymavlink's ``check_signature`` stores a frame's timestamp
for its stream *before* comparing the signature, so one forged frame with a far-future
timestamp would make every genuine frame of that stream look replayed; ``parse_bytes``
undoes that store when the signature is wrong (the C library checks the signature first).
"""

from __future__ import annotations

import struct
from collections import Counter
from collections.abc import Collection
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.compiled import check_built_from_current_source, not_built

try:
    from swarm.mavlink import _frame
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise not_built("swarm.mavlink._frame", "swarm/mavlink/_frame.c") from exc

check_built_from_current_source(Path(_frame.__file__), Path(__file__).with_name("_frame.c"))

_MAGIC_V2 = mavlink2.PROTOCOL_MARKER_V2
# What a console prints: printable ASCII, tab, newline, carriage return.
_CONSOLE_BYTES = bytes(range(0x20, 0x7F)) + b"\t\n\r"


def console_text(msg: Any) -> bytes | None:
    """The text of ``msg`` if it is a run of console text between frames (a BAD_DATA of
    printable ASCII that pymavlink skipped looking for a frame's first byte), else None."""
    if msg.get_type() != "BAD_DATA" or msg.reason != "Bad prefix":
        return None
    data = bytes(msg.data)
    return data if data and not data.translate(None, _CONSOLE_BYTES) else None


def reset_parser(parser: mavlink2.MAVLink) -> None:
    """Forget any partial frame held by ``parser``."""
    parser.buf = bytearray()
    parser.buf_index = 0
    parser.expected_length = mavlink2.HEADER_LEN_V1 + 2


def parse_bytes(parser: mavlink2.MAVLink, data: bytes, rejections: Counter[str], *,
                datagram: bool, known_undecoded: Collection[int] = (),
                console: bytearray | None = None) -> list[Any]:
    """The complete, known messages in ``data``; everything else counted in ``rejections``
    (``bad_data``, ``unknown_message``, ``truncated``, ``parser_error:<type>``; with signing
    also ``unsigned``, ``bad_signature``, ``stale_signature``).
    ``datagram``: ``data`` is one whole UDP datagram (a leftover is a truncated frame).
    ``known_undecoded``: ids of messages outside the dialect that the caller decodes itself
    (e.g. PX4's EVENT, ``swarm.mavlink.px4_events``): returned as pymavlink's UNKNOWN_<id> objects,
    their checksum unchecked (the caller checks it), not counted.
    ``console``: console text between frames (``console_text``) is appended here instead of
    being counted as ``bad_data`` (None: it is counted)."""
    try:
        if parser.signing.secret_key is None:
            messages = parser.parse_buffer(bytes(data)) or []
        else:
            messages = _parse_signed(parser, bytes(data), rejections)
    except Exception as exc:  # pymavlink should not raise with robust parsing; be safe
        rejections[f"parser_error:{type(exc).__name__}"] += 1
        reset_parser(parser)
        return []
    out: list[Any] = []
    for msg in messages:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            text = console_text(msg)
            if console is not None and text is not None:
                console += text
            else:
                rejections["bad_data"] += 1
        elif kind.startswith("UNKNOWN"):
            if known_undecoded and int(kind[len("UNKNOWN_"):]) in known_undecoded:
                out.append(msg)
            else:
                rejections["unknown_message"] += 1
        else:
            out.append(msg)
    if datagram and parser.buf_len() > 0:
        rejections["truncated"] += 1
        reset_parser(parser)
    return out


def _parse_signed(parser: mavlink2.MAVLink, data: bytes,
                  rejections: Counter[str]) -> list[Any]:
    """``parse_buffer`` one frame at a time (as it does itself), counting the frames
    pymavlink refuses for their signature and undoing its premature timestamp store."""
    signing = parser.signing
    out: list[Any] = []
    chunk = data
    while True:
        before = dict(signing.stream_timestamps)  # one entry per peer stream: tiny
        msg = parser.parse_char(chunk)
        chunk = b""
        if msg is None:
            return out
        if msg.get_type() != "BAD_DATA" or msg.reason != "Invalid signature":
            out.append(msg)
            continue
        frame = msg.data
        if not (frame[0] == _MAGIC_V2 and frame[2] & mavlink2.MAVLINK_IFLAG_SIGNED):
            rejections["unsigned"] += 1
        elif signing.stream_timestamps != before:  # the timestamp passed, the signature not
            signing.stream_timestamps.clear()
            signing.stream_timestamps.update(before)
            rejections["bad_signature"] += 1
        else:
            rejections["stale_signature"] += 1


class FastFrame:
    """Pack / unpack one array-free message type the way pymavlink does, minus its overhead.

    ``pack(mav, *fields)`` takes the fields in pymavlink's wire order (``ordered_fieldnames``
    of the message class) and returns the frame ``mav.send`` would write, advancing
    ``mav``'s sequence and byte counters the same way; None if pymavlink must do it (signing
    on, or a send callback to call). ``unpack(data)`` returns (system id, component id,
    fields in wire order) or None (see the module docstring).
    """

    def __init__(self, message_class: type[Any]) -> None:  # a pymavlink message class
        if any(length != 1 for length in message_class.lengths):
            raise ValueError(f"{message_class.msgname} has array fields")
        self.message_class = message_class
        self.msgid: int = message_class.id
        self.crc_extra: int = message_class.crc_extra
        self.fields: tuple[str, ...] = tuple(message_class.ordered_fieldnames)
        self._struct: struct.Struct = message_class.unpacker

    def pack(self, mav: mavlink2.MAVLink, *fields: Any) -> bytes | None:
        if mav.signing.sign_outgoing or mav.send_callback is not None:
            return None
        frame: bytes = _frame.frame_v2(self._struct.pack(*fields), mav.seq, mav.srcSystem,
                                       mav.srcComponent, self.msgid, self.crc_extra)
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(frame)
        return frame

    def unpack(self, data: bytes) -> tuple[int, int, tuple[Any, ...]] | None:
        framed = _frame.payload_v2(data, self.msgid, self.crc_extra, self._struct.size)
        if framed is None:
            return None
        system, component, payload = framed
        return system, component, self._struct.unpack(payload)

    def message(self, data: bytes) -> Any | None:
        """``unpack`` as the pymavlink message object ``parse_bytes`` would return."""
        unpacked = self.unpack(data)
        if unpacked is None:
            return None
        system, component, values = unpacked
        by_name = dict(zip(self.fields, values, strict=True))
        msg = self.message_class(*(by_name[name] for name in self.message_class.fieldnames))
        msg._header = mavlink2.MAVLink_header(self.msgid, 0, data[3], data[1], data[4],
                                              system, component)
        return msg


LOCAL_POSITION_NED = FastFrame(mavlink2.MAVLink_local_position_ned_message)
# SET_POSITION_TARGET_LOCAL_NED type masks the swarm sends (bits set = fields ignored).
VELOCITY_ONLY_TYPE_MASK = 0x0DC7  # ignore x, y, z, afx, afy, afz, yaw, yaw rate
POSITION_ONLY_TYPE_MASK = 0x0DF8  # ignore vx, vy, vz, afx, afy, afz, yaw, yaw rate
# Setpoints along the command reference, per flavour (yaw and yaw rate ignored):
# - ArduCopter: position + velocity (0x0DC0). GUIDED moves its position target on along the
#   velocity between setpoints, and would integrate an acceleration into the velocity too:
#   when the agent is lost, the vehicle must coast at its last velocity until GUID_TIMEOUT
#   (what the other drones' collision rows assume), not speed up (seen on SITL: 0.17 → 0.29
#   m/s within 2 s after a kill -9 with acceleration feed-forward).
# - PX4: position + velocity + acceleration feed-forward (0x0C00); OFFBOARD does not
#   extrapolate a setpoint and holds after COM_OF_LOSS_T.
TRACKED_TYPE_MASK = {"ardupilot": 0x0DC0, "px4": 0x0C00}
SET_POSITION_TARGET_LOCAL_NED = FastFrame(mavlink2.MAVLink_set_position_target_local_ned_message)
