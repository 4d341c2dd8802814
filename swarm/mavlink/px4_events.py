"""PX4's EVENT messages (MAVLink 410): check, decode and name them.

Why: PX4 (v1.15) says why it refuses to arm, and which pre-flight checks fail, in EVENT
messages (its "events interface"), not in STATUSTEXT. pymavlink 2.4.50 has no definition of
EVENT in any dialect, so its parser hands these frames over as ``MAVLink_unknown`` (type
``UNKNOWN_410``, ``get_msgId()`` = MAVLINK_MSG_ID_UNKNOWN, the whole frame as its buffer) and
does not check their checksum. This module does both: it checks the frame's MAVLink 2 X.25
checksum with EVENT's CRC_EXTRA (derived from the message definition as the MAVLink spec
does; pymavlink's own ``x25crc``), unpacks the payload (re-padding the trailing zero bytes
MAVLink 2 strips) into a ``Px4Event`` and names the event from the table generated from PX4's
source (``swarm.mavlink.px4_event_names``, made by ``tools/px4_event_names.py``).

Event ids: PX4 computes them at compile time from the event's name, ``events::ID("name")`` in
``platforms/common/include/px4_platform_common/events.h`` (v1.15.4, matching
``Tools/px4events/srcparser.py``): the low 24 bits of the 32-bit FNV-1a hash of the name's
bytes, with the autopilot component (1) in the top 8 bits (``px4_event_id``).

Log levels (libevents; EVENT's ``log_levels``: external in the low 4 bits, internal in the
high 4): emergency 0, alert 1, critical 2, error 3, warning 4, notice 5, info 6, debug 7,
protocol 8, disabled 9. Arming-check and health results come at levels from "critical" to
"info" (PX4 v1.15.4 SITL before it can arm: ``check_modes_attitude`` critical,
``check_estimator_hor_vel_not_stable`` error, ``check_modes_manual_control`` warning, and
``commander_arm_denied_resolve_failures`` critical for each refused request); the "protocol"
ones (``commander_arming_check_summary``, ``commander_health_summary``) are the bitfield
summaries a ground station keeps its checklist from.

``UNDECODED_MESSAGES`` lists the ids PX4 sends that pymavlink 2.4.50 does not decode, so that
a link can count them as known-but-not-decoded rather than as junk.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.generator.mavcrc import x25crc

from swarm.mavlink.px4_event_names import EVENT_NAMES, PX4_VERSION

EVENT_MSG_ID = 410
CURRENT_EVENT_SEQUENCE_MSG_ID = 411

# MAVLink message ids PX4 v1.15 sends that pymavlink 2.4.50's ardupilotmega dialect does not
# define (UNKNOWN_<id> when parsed). Seen on PX4 v1.15.4 SITL's onboard link: 8, 380, 410, 411,
# 436 (names from MAVLink's common.xml / development.xml of the commit PX4 v1.15.4 builds
# with); 412, 413, 435 and 437 belong to the same two protocols (events, standard modes).
UNDECODED_MESSAGES: Mapping[int, str] = {
    8: "LINK_NODE_STATUS",
    380: "TIME_ESTIMATE_TO_TARGET",
    EVENT_MSG_ID: "EVENT",
    CURRENT_EVENT_SEQUENCE_MSG_ID: "CURRENT_EVENT_SEQUENCE",
    412: "REQUEST_EVENT",
    413: "RESPONSE_EVENT_ERROR",
    435: "AVAILABLE_MODES",
    436: "CURRENT_MODE",
    437: "AVAILABLE_MODES_MONITOR",
}

# EVENT's fields in wire order (MAVLink 2 sorts them by type size, largest first):
# (type, name, array length or 0). No extension fields.
EVENT_FIELDS: tuple[tuple[str, str, int], ...] = (
    ("uint32_t", "id", 0),
    ("uint32_t", "event_time_boot_ms", 0),
    ("uint16_t", "sequence", 0),
    ("uint8_t", "destination_component", 0),
    ("uint8_t", "destination_system", 0),
    ("uint8_t", "log_levels", 0),
    ("uint8_t", "arguments", 40),
)
_EVENT_PAYLOAD = struct.Struct("<IIHBBB40s")
EVENT_PAYLOAD_LEN = _EVENT_PAYLOAD.size  # 53 bytes
EVENT_ARGUMENTS_LEN = 40

LOG_LEVELS: tuple[str, ...] = ("emergency", "alert", "critical", "error", "warning", "notice",
                               "info", "debug", "protocol", "disabled")

PX4_AUTOPILOT_COMPONENT = 1  # the top 8 bits of every events::ID() id
_FNV1A_32_OFFSET = 0x811C9DC5
_FNV1A_32_PRIME = 0x01000193

_MAGIC_V2 = 0xFD
_HEADER_LEN_V2 = 10  # magic, len, incompat, compat, seq, sys, comp, msgid (3 bytes)
_CHECKSUM_LEN = 2
_SIGNATURE_LEN = 13
_IFLAG_SIGNED = 0x01


@dataclass(frozen=True)
class Px4Event:
    """One EVENT message, decoded.

    ``arguments`` are the event's 40 argument bytes (little-endian values, laid out as the
    event's definition says; zero bytes past the last argument). ``name`` is None for an id
    not in the table of PX4 ``PX4_VERSION``'s events.
    """

    event_id: int
    name: str | None
    time_boot_ms: int  # [ms] autopilot's time since boot when the event happened
    sequence: int  # uint16, wraps; PX4 starts near 65535 so that it wraps soon
    log_level_external: str  # what a user should see it as: "error", "warning", ...
    log_level_internal: str  # what the autopilot logs it as
    arguments: bytes
    destination_system: int  # 0: broadcast
    destination_component: int  # 0: broadcast

    @property
    def component_id(self) -> int:
        """The id's namespace byte: 1 for PX4's own events (``events::ID``)."""
        return self.event_id >> 24


# -- ids and names -------------------------------------------------------------------------------


def fnv1a_32(data: bytes) -> int:
    """32-bit FNV-1a hash of ``data`` (offset basis 0x811c9dc5, prime 0x01000193)."""
    value = _FNV1A_32_OFFSET
    for byte in data:
        value = ((value ^ byte) * _FNV1A_32_PRIME) & 0xFFFFFFFF
    return value


def px4_event_id(name: str) -> int:
    """The id PX4 gives the event named ``name`` (``events::ID("name")``):
    ``(fnv1a_32(name) & 0xffffff) | 1 << 24``. ValueError for a non-ASCII name."""
    return (fnv1a_32(name.encode("ascii")) & 0xFFFFFF) | PX4_AUTOPILOT_COMPONENT << 24


def log_level_name(level: int) -> str:
    """The libevents name of log level ``level`` (0..15); "level<N>" past "disabled" (9)."""
    if not 0 <= level <= 15:
        raise ValueError(f"log level {level} out of range 0..15")
    return LOG_LEVELS[level] if level < len(LOG_LEVELS) else f"level{level}"


def log_level_number(name: str) -> int:
    """Inverse of ``log_level_name``; ValueError for anything else."""
    if name in LOG_LEVELS:
        return LOG_LEVELS.index(name)
    if name.startswith("level") and name[5:].isdigit() and 10 <= int(name[5:]) <= 15:
        return int(name[5:])
    raise ValueError(f"unknown log level {name!r} (expected one of {', '.join(LOG_LEVELS)})")


def describe(event: Px4Event) -> str:
    """One line for a log or a refusal message, e.g.
    ``PX4 check_estimator_hor_vel_not_stable (error)``, or for an id not in the table
    ``PX4 event 0x1234abcd (warning; not a known v1.15 event)``."""
    if event.name is not None:
        return f"PX4 {event.name} ({event.log_level_external})"
    return (f"PX4 event 0x{event.event_id:08x} ({event.log_level_external}; "
            f"not a known {_major_minor(PX4_VERSION)} event)")


def _major_minor(version: str) -> str:
    return ".".join(version.split(".")[:2])


# -- MAVLink framing -----------------------------------------------------------------------------


def mavlink_crc_extra(message_name: str, fields: Sequence[tuple[str, str, int]]) -> int:
    """A message's CRC_EXTRA as the MAVLink generator derives it: X.25 CRC of
    ``"NAME "`` then ``"type name "`` per non-extension field in wire order (each array's
    length as one byte after it), folded to 8 bits (low byte XOR high byte)."""
    crc = x25crc(f"{message_name} ".encode())
    for type_name, field_name, array_length in fields:
        crc.accumulate(f"{type_name} {field_name} ".encode())
        if array_length:
            crc.accumulate(bytes((array_length,)))
    return (crc.crc & 0xFF) ^ (crc.crc >> 8)


EVENT_CRC_EXTRA = mavlink_crc_extra("EVENT", EVENT_FIELDS)  # 160 = MAVLINK_MSG_ID_EVENT_CRC


def frame_message_id(frame: bytes) -> int | None:
    """The message id in a MAVLink 2 frame's header; None if ``frame`` is not one."""
    if len(frame) < _HEADER_LEN_V2 or frame[0] != _MAGIC_V2:
        return None
    return frame[7] | frame[8] << 8 | frame[9] << 16


def frame_payload(frame: bytes, crc_extra: int) -> bytes | None:
    """The (zero-stripped) payload of one whole MAVLink 2 frame if its length adds up and its
    checksum holds with ``crc_extra``, else None. A signature is skipped, not checked (that is
    pymavlink's job on a signed link)."""
    if len(frame) < _HEADER_LEN_V2 + _CHECKSUM_LEN or frame[0] != _MAGIC_V2:
        return None
    end = _HEADER_LEN_V2 + frame[1]
    signature_len = _SIGNATURE_LEN if frame[2] & _IFLAG_SIGNED else 0
    if len(frame) != end + _CHECKSUM_LEN + signature_len:
        return None
    crc = x25crc(frame[1:end])
    crc.accumulate(bytes((crc_extra,)))
    if frame[end] | frame[end + 1] << 8 != crc.crc:
        return None
    return bytes(frame[_HEADER_LEN_V2:end])


def pack_frame(message_id: int, payload: bytes, crc_extra: int, *, seq: int, system_id: int,
               component_id: int) -> bytes:
    """An unsigned MAVLink 2 frame of ``payload`` (trailing zero bytes stripped, one kept)."""
    stripped = payload.rstrip(b"\x00") or payload[:1]
    frame = bytearray((_MAGIC_V2, len(stripped), 0, 0, seq & 0xFF, system_id, component_id,
                       message_id & 0xFF, message_id >> 8 & 0xFF, message_id >> 16 & 0xFF))
    frame += stripped
    crc = x25crc(frame[1:])
    crc.accumulate(bytes((crc_extra,)))
    frame += struct.pack("<H", crc.crc)
    return bytes(frame)


# -- EVENT ---------------------------------------------------------------------------------------


def decode_event_payload(payload: bytes, names: Mapping[int, str] = EVENT_NAMES) -> Px4Event:
    """The event in an EVENT payload: zero-stripped (MAVLink 2) ones are padded back to 53
    bytes; bytes past 53 (extension fields of a later definition) are ignored, as MAVLink
    receivers do."""
    padded = bytes(payload[:EVENT_PAYLOAD_LEN]).ljust(EVENT_PAYLOAD_LEN, b"\x00")
    (event_id, time_boot_ms, sequence, destination_component, destination_system, log_levels,
     arguments) = _EVENT_PAYLOAD.unpack(padded)
    return Px4Event(event_id=event_id, name=names.get(event_id), time_boot_ms=time_boot_ms,
                    sequence=sequence, log_level_external=log_level_name(log_levels & 0x0F),
                    log_level_internal=log_level_name(log_levels >> 4), arguments=arguments,
                    destination_system=destination_system,
                    destination_component=destination_component)


def encode_event_payload(event: Px4Event) -> bytes:
    """The full 53-byte EVENT payload of ``event`` (``name`` is not sent: the id says it).
    ValueError if ``arguments`` is longer than 40 bytes (shorter ones are zero-padded)."""
    if len(event.arguments) > EVENT_ARGUMENTS_LEN:
        raise ValueError(f"event arguments are {len(event.arguments)} bytes, at most "
                         f"{EVENT_ARGUMENTS_LEN} fit")
    log_levels = (log_level_number(event.log_level_internal) << 4
                  | log_level_number(event.log_level_external))
    return _EVENT_PAYLOAD.pack(event.event_id, event.time_boot_ms, event.sequence,
                               event.destination_component, event.destination_system,
                               log_levels, event.arguments)


def pack_event_frame(event: Px4Event, *, seq: int, system_id: int,
                     component_id: int = PX4_AUTOPILOT_COMPONENT) -> bytes:
    """``event`` as the MAVLink 2 frame PX4 would send (unsigned, payload zero-stripped)."""
    return pack_frame(EVENT_MSG_ID, encode_event_payload(event), EVENT_CRC_EXTRA, seq=seq,
                      system_id=system_id, component_id=component_id)


def event_from_message(msg: Any, names: Mapping[int, str] = EVENT_NAMES) -> Px4Event | None:
    """The ``Px4Event`` in one pymavlink message as our parser delivers it; None when it is
    not an EVENT or its frame's length or checksum is wrong.

    pymavlink 2.4.50 delivers EVENT as ``MAVLink_unknown``, whose buffer is the whole frame
    (checksum unchecked): the id comes from the frame's header and the checksum is checked
    here. A pymavlink whose dialect defines EVENT decodes and checks it itself; its fields
    are then taken as they are.
    """
    if msg.get_msgId() == EVENT_MSG_ID and hasattr(msg, "log_levels"):
        return decode_event_payload(
            _EVENT_PAYLOAD.pack(msg.id, msg.event_time_boot_ms, msg.sequence,
                                msg.destination_component, msg.destination_system,
                                msg.log_levels, bytes(msg.arguments)), names)
    if not msg.get_type().startswith("UNKNOWN_"):
        return None
    frame = bytes(msg.get_msgbuf())
    if frame_message_id(frame) != EVENT_MSG_ID:
        return None
    payload = frame_payload(frame, EVENT_CRC_EXTRA)
    return None if payload is None else decode_event_payload(payload, names)


def message_source(msg: Any) -> tuple[int, int]:
    """(system id, component id) of the sender of a pymavlink message. For ``MAVLink_unknown``
    pymavlink leaves both 0 (it returns before reading the header into the message), so
    they are read from its frame's header; 0, 0 if that is not a MAVLink 2 frame."""
    if not msg.get_type().startswith("UNKNOWN_"):
        return msg.get_srcSystem(), msg.get_srcComponent()
    frame = bytes(msg.get_msgbuf())
    if frame_message_id(frame) is None:
        return 0, 0
    return frame[5], frame[6]


def undecoded_message_name(msg: Any) -> str | None:
    """"EVENT", "CURRENT_EVENT_SEQUENCE", ... for a message pymavlink could not decode
    (``UNKNOWN_<id>``) whose id is one PX4 is known to send; None for anything else."""
    kind = msg.get_type()
    if not kind.startswith("UNKNOWN_") or not kind[8:].isdigit():
        return None
    return UNDECODED_MESSAGES.get(int(kind[8:]))
